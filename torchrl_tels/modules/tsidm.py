"""The T-symmetry enforced inverse dynamics model (TS-IDM), paper §3.1."""
from __future__ import annotations

import os
from typing import Any, Sequence

import torch
from torch import nn

from torchrl.modules import MLP

from torchrl_tels.checkpoint import atomic_save, CheckpointError, load_checkpoint

__all__ = ["TSIDM", "jvp", "squared_norm", "standardize"]

#: Floor of the latent standard deviation, so a constant latent dimension does not blow up.
LATENT_STD_EPS = 1e-6


def standardize(x: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``(x - loc) / scale``: the fixed-scale latent of ``TSIDM(latent_standardization=True)``."""
    return (x - loc) / scale


def squared_norm(x: torch.Tensor, dim_reduction: str = "sum") -> torch.Tensor:
    r"""The paper's :math:`\|x\|_2^2` over the last dimension, per sample.

    ``"sum"`` is the norm as written; ``"mean"`` divides it by the size of the
    vector, which rebalances terms of different sizes (states vs actions).
    """
    if dim_reduction == "sum":
        return x.pow(2).sum(-1)
    if dim_reduction == "mean":
        return x.pow(2).mean(-1)
    raise ValueError(f"dim_reduction must be 'sum' or 'mean', got {dim_reduction!r}.")


def jvp(
    function: nn.Module, primal: torch.Tensor, tangent: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns ``(function(primal), J_function(primal) @ tangent)`` per sample.

    This is forward-mode differentiation: the tangent travels through the
    network next to the input, in one extra pass, and the per-sample Jacobian
    is never built (TSRL's ``vmap(jacrev)`` builds it and costs several times
    more). The result stays differentiable with respect to the parameters and
    to ``tangent``, as Eqs. (4) and (5) need: both sides of those losses train.

    For a plain stack of ``Linear`` and ``ReLU`` layers (every TS-IDM
    encoder/decoder) the tangent is pushed layer by layer (``W t``, then
    masked by the ReLU's active set), which is the same forward-mode rule
    without the dual-tensor overhead of :func:`torch.func.jvp`; anything else
    goes through :func:`torch.func.jvp`.
    """
    if isinstance(function, nn.Sequential) and all(
        isinstance(layer, (nn.Linear, nn.ReLU)) for layer in function
    ):
        output = primal
        for layer in function:
            if isinstance(layer, nn.Linear):
                output = layer(output)
                tangent = tangent @ layer.weight.transpose(0, 1)
            else:
                tangent = tangent * (output > 0)
                output = torch.relu(output)
        return output, tangent
    return torch.func.jvp(function, (primal,), (tangent,))


class TSIDM(nn.Module):
    r"""T-symmetry enforced inverse dynamics model (paper §3.1, Fig. 1 left).

    Six sub-networks, each a :class:`torchrl.modules.MLP` with two ReLU hidden
    layers (Table 10):

    * state encoder :math:`\phi_s(s) = z_s` and state decoder :math:`\psi_s(z_s) = \hat s`;
    * latent inverse dynamics :math:`h_{inv}(z_s, z_{s'}) = z_a` (dropout 0.1)
      and action decoder :math:`\psi_a(z_a) = \hat a`;
    * latent ODE forward dynamics :math:`h_{fwd}(z_s, z_a) = \dot z_s` and
      reverse dynamics :math:`h_{rvs}(z_{s'}, z_a) = -\dot z_s`.

    States are normalized inside the module (Table 10, "State normalize: True")
    with ``obs_loc``/``obs_scale`` buffers, so a saved TS-IDM carries its
    normalization. Everything in the latent space and the decoder output
    :math:`\hat s` live in that normalized space; :math:`\dot s` is
    ``normalize(s') - normalize(s)``.

    The paper does not give the latent sizes. As TSRL did, the latent state
    size defaults to the observation size and the latent action size to the
    action size.

    Args:
        observation_dim: size of the raw observation.
        action_dim: size of the action.
        latent_state_dim: size of :math:`z_s`. Defaults to ``observation_dim``.
        latent_action_dim: size of :math:`z_a`. Defaults to ``action_dim``.
        encoder_cells, decoder_cells, inverse_cells, action_decoder_cells,
        dynamics_cells: hidden widths (Table 10 defaults).
        inverse_dropout: dropout in :math:`h_{inv}` (Table 10: 0.1).
        latent_standardization: if ``True``, :math:`z_s` is the encoder's output
            standardized per dimension, :math:`z_s = (e(s) - \mu_e) / \sigma_e`.
            Eq. (7) is invariant to rescaling the latent space except for
            :math:`\ell_{dyn}` and :math:`\ell_{T\text{-}sym}`, which shrink as
            :math:`c^2`; a fixed-scale latent removes that direction. Training
            (:class:`~torchrl_tels.objectives.TSIDMLoss`) standardizes with the
            batch's statistics, gradient included, so the scale of :math:`e`
            carries no gradient; acting uses the ``latent_loc``/``latent_scale``
            buffers, set from data by :meth:`fit_latent_standardization` and saved
            with the model. Not in the paper; off by default.
        obs_loc, obs_scale: state normalization statistics; identity if omitted.
            Use :meth:`set_state_normalization` to fit them from data.
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        latent_state_dim: int | None = None,
        latent_action_dim: int | None = None,
        encoder_cells: Sequence[int] = (512, 256),
        decoder_cells: Sequence[int] = (256, 512),
        inverse_cells: Sequence[int] = (1024, 1024),
        action_decoder_cells: Sequence[int] = (512, 512),
        dynamics_cells: Sequence[int] = (256, 256),
        inverse_dropout: float | None = 0.1,
        latent_standardization: bool = False,
        obs_loc: torch.Tensor | None = None,
        obs_scale: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        for name, value in (("observation_dim", observation_dim), ("action_dim", action_dim)):
            if int(value) <= 0:
                raise ValueError(f"TSIDM: {name} must be a positive integer, got {value}.")
        self.observation_dim = int(observation_dim)
        self.action_dim = int(action_dim)
        self.latent_state_dim = int(latent_state_dim or observation_dim)
        self.latent_action_dim = int(latent_action_dim or action_dim)
        zs, za = self.latent_state_dim, self.latent_action_dim

        def mlp(in_features, out_features, cells, dropout=None):
            return MLP(
                in_features=in_features,
                out_features=out_features,
                num_cells=list(cells),
                activation_class=nn.ReLU,
                dropout=dropout,
            )

        self.state_encoder = mlp(self.observation_dim, zs, encoder_cells)
        self.state_decoder = mlp(zs, self.observation_dim, decoder_cells)
        self.inverse_dynamics = mlp(2 * zs, za, inverse_cells, inverse_dropout)
        self.action_decoder = mlp(za, self.action_dim, action_decoder_cells)
        self.forward_dynamics = mlp(zs + za, zs, dynamics_cells)
        self.reverse_dynamics = mlp(zs + za, zs, dynamics_cells)

        if obs_loc is None:
            obs_loc = torch.zeros(self.observation_dim)
        if obs_scale is None:
            obs_scale = torch.ones(self.observation_dim)
        self.register_buffer("obs_loc", torch.zeros(self.observation_dim))
        self.register_buffer("obs_scale", torch.ones(self.observation_dim))
        self.set_state_normalization(obs_loc, obs_scale)
        self.latent_standardization = bool(latent_standardization)
        if self.latent_standardization:
            self.register_buffer("latent_loc", torch.zeros(zs))
            self.register_buffer("latent_scale", torch.ones(zs))

    # ------------------------------------------------------------------ config
    def config(self) -> dict:
        """The constructor arguments (without weights), for saving alongside the state dict."""
        widths = {
            name: [m.out_features for m in getattr(self, attr) if isinstance(m, nn.Linear)][:-1]
            for name, attr in (
                ("encoder_cells", "state_encoder"),
                ("decoder_cells", "state_decoder"),
                ("inverse_cells", "inverse_dynamics"),
                ("action_decoder_cells", "action_decoder"),
                ("dynamics_cells", "forward_dynamics"),
            )
        }
        dropout = self.inverse_dynamics.dropout
        return {
            "observation_dim": self.observation_dim,
            "action_dim": self.action_dim,
            "latent_state_dim": self.latent_state_dim,
            "latent_action_dim": self.latent_action_dim,
            "inverse_dropout": dropout,
            "latent_standardization": self.latent_standardization,
            **widths,
        }

    @torch.no_grad()
    def set_state_normalization(
        self, loc: torch.Tensor, scale: torch.Tensor, eps: float = 1e-3
    ) -> None:
        """Sets the state normalization; ``scale`` is floored at ``eps`` so constant dims do not blow up."""
        loc = torch.as_tensor(loc, dtype=self.obs_loc.dtype).reshape(-1)
        scale = torch.as_tensor(scale, dtype=self.obs_scale.dtype).reshape(-1)
        for name, value in (("loc", loc), ("scale", scale)):
            if value.shape != (self.observation_dim,):
                raise ValueError(
                    f"TSIDM state normalization {name} must have shape ({self.observation_dim},), "
                    f"got {tuple(value.shape)}."
                )
            if not torch.isfinite(value).all():
                raise ValueError(f"TSIDM state normalization {name} contains NaN or inf.")
        self.obs_loc.copy_(loc)
        self.obs_scale.copy_(scale.clamp_min(eps))

    @torch.no_grad()
    def fit_state_normalization(self, observations: torch.Tensor) -> None:
        """Fits mean/std of the states from data (Table 10: "State normalize: True")."""
        observations = observations.reshape(-1, self.observation_dim)
        self.set_state_normalization(observations.mean(0), observations.std(0))

    @torch.no_grad()
    def fit_latent_standardization(self, observations: torch.Tensor, batch_size: int = 65536) -> None:
        """Sets ``latent_loc``/``latent_scale`` to the mean/std of the encoder's output over ``observations``."""
        if not self.latent_standardization:
            raise ValueError("fit_latent_standardization: this TSIDM was built with latent_standardization=False.")
        observations = observations.reshape(-1, self.observation_dim)
        raw = torch.cat([self.state_encoder(self.normalize_state(chunk)) for chunk in observations.split(batch_size)])
        self.latent_loc.copy_(raw.mean(0))
        self.latent_scale.copy_(raw.std(0).clamp_min(LATENT_STD_EPS))

    # --------------------------------------------------------------- the maps
    def normalize_state(self, observation: torch.Tensor) -> torch.Tensor:
        # Gym envs emit float64 observations; the networks run in the buffers' dtype.
        observation = observation.to(self.obs_loc.dtype)
        return (observation - self.obs_loc) / self.obs_scale

    def embed_state(self, normalized_state: torch.Tensor) -> torch.Tensor:
        """:math:`z_s = \\phi_s(s)` from a normalized state (standardized when the model is)."""
        latent = self.state_encoder(normalized_state)
        if self.latent_standardization:
            latent = standardize(latent, self.latent_loc, self.latent_scale)
        return latent

    def encode_state(self, observation: torch.Tensor) -> torch.Tensor:
        """:math:`z_s = \\phi_s(s)` from a raw (unnormalized) observation."""
        return self.embed_state(self.normalize_state(observation))

    @torch.no_grad()
    def encode_states(self, observation: torch.Tensor, chunk_size: int = 65536) -> torch.Tensor:
        """:meth:`encode_state` of many observations without gradients, ``chunk_size`` rows at a time: a
        dataset's worth at once would hold every hidden layer's activations for every row (gigabytes at 1M)."""
        flat = observation.reshape(-1, observation.shape[-1])
        latent = torch.cat([self.encode_state(chunk) for chunk in flat.split(chunk_size)])
        return latent.reshape(*observation.shape[:-1], latent.shape[-1])

    def decode_state(self, latent_state: torch.Tensor) -> torch.Tensor:
        """:math:`\\hat s = \\psi_s(z_s)`, in the normalized state space."""
        return self.state_decoder(latent_state)

    def infer_latent_action(
        self, latent_state: torch.Tensor, next_latent_state: torch.Tensor
    ) -> torch.Tensor:
        """:math:`z_a = h_{inv}(z_s, z_{s'})`."""
        return self.inverse_dynamics(latent_state, next_latent_state)

    def decode_action(self, latent_action: torch.Tensor) -> torch.Tensor:
        """:math:`\\hat a = \\psi_a(z_a)`."""
        return self.action_decoder(latent_action)

    def latent_forward(self, latent_state: torch.Tensor, latent_action: torch.Tensor) -> torch.Tensor:
        """:math:`\\dot z_s = h_{fwd}(z_s, z_a)`."""
        return self.forward_dynamics(latent_state, latent_action)

    def latent_reverse(
        self, next_latent_state: torch.Tensor, latent_action: torch.Tensor
    ) -> torch.Tensor:
        """:math:`-\\dot z_s = h_{rvs}(z_{s'}, z_a)`."""
        return self.reverse_dynamics(next_latent_state, latent_action)

    def tsym_consistency(
        self,
        latent_state: torch.Tensor,
        latent_action: torch.Tensor,
        dim_reduction: str = "sum",
    ) -> torch.Tensor:
        r"""Eq. (6), per sample: :math:`\|h_{fwd}(z_s, z_a) + h_{rvs}(z_s + h_{fwd}(z_s, z_a), z_a)\|_2^2`.

        The reverse model is evaluated at :math:`z_{s'} = z_s + \dot z_s` as the
        paper states below Eq. (6), which couples :math:`h_{fwd}` and
        :math:`h_{rvs}`. Returns a tensor of shape ``latent_state.shape[:-1]``;
        a large value flags a latent transition that does not follow the
        learned dynamics, which is why the guide policy uses it as a penalty.
        """
        z_dot = self.latent_forward(latent_state, latent_action)
        reverse = self.latent_reverse(latent_state + z_dot, latent_action)
        return squared_norm(z_dot + reverse, dim_reduction)

    # ------------------------------------------------------------ save/load
    CHECKPOINT_FORMAT = "torchrl_tels.tsidm/v1"

    def checkpoint_payload(self, metadata: dict[str, Any] | None = None) -> dict[str, Any]:
        """What :meth:`save` writes: format, config, weights (with the normalization) and ``metadata``.

        Other checkpoints that carry a TS-IDM (the deployment monitor's) embed this dict.
        """
        return {
            "format": self.CHECKPOINT_FORMAT,
            "config": self.config(),
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
            "metadata": dict(metadata or {}),
        }

    def save(self, path: str | os.PathLike, metadata: dict[str, Any] | None = None) -> None:
        """Writes config, weights (with the state normalization) and ``metadata`` atomically."""
        atomic_save(self.checkpoint_payload(metadata), path)

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        *,
        observation_dim: int | None = None,
        action_dim: int | None = None,
    ) -> "TSIDM":
        """Rebuilds a TS-IDM saved by :meth:`save`, in eval mode.

        ``observation_dim``/``action_dim``, when given, must match the file:
        a TS-IDM trained for another env is refused with a clear error.
        """
        payload = load_checkpoint(path, cls.CHECKPOINT_FORMAT)
        return cls.from_payload(payload, path, observation_dim=observation_dim, action_dim=action_dim)

    @classmethod
    def from_payload(
        cls,
        payload: dict[str, Any],
        source: str | os.PathLike,
        *,
        observation_dim: int | None = None,
        action_dim: int | None = None,
    ) -> "TSIDM":
        """Rebuilds a TS-IDM from :meth:`checkpoint_payload`'s dict (read from ``source``), in eval mode."""
        config = payload["config"]
        for name, expected in (("observation_dim", observation_dim), ("action_dim", action_dim)):
            if expected is not None and int(config[name]) != int(expected):
                raise CheckpointError(
                    f"TS-IDM checkpoint {source} has {name}={config[name]}, but this "
                    f"environment/dataset has {name}={expected}: it was trained for another task."
                )
        tsidm = cls(**config)
        try:
            tsidm.load_state_dict(payload["state_dict"])
        except RuntimeError as err:
            raise CheckpointError(f"TS-IDM checkpoint {source} does not match its own config: {err}") from None
        tsidm.metadata = payload.get("metadata", {})
        return tsidm.eval()
