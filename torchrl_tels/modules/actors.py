"""Latent value, guide policy and the TELS actor of Eq. (11), as tensordict modules."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict.nn import (
    NormalParamExtractor,
    ProbabilisticTensorDictModule,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictSequential,
)
from torch import nn
from torch.distributions import Independent, Normal
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ValueOperator

from torchrl_tels.modules.tsidm import TSIDM

__all__ = [
    "GUIDE_KEY",
    "LATENT_KEY",
    "IndependentNormal",
    "LatentActionHead",
    "StateEncoder",
    "make_guide_policy",
    "make_latent_value",
    "make_tels_actor",
]

#: Where the encoded state lives in a tensordict (also TSIDMEncoderTransform's default).
LATENT_KEY = "latent"
#: Where the guide policy writes its proposed next latent state :math:`z_{s'}^*`.
GUIDE_KEY = "guide_latent"


class IndependentNormal(Independent):
    """A diagonal Gaussian over the next latent, one log-probability per sample.

    No tanh squashing: latent states are unbounded. Its ``deterministic_sample``
    is the mean, which TorchRL's deterministic exploration mode uses.
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor):
        super().__init__(Normal(loc, scale), 1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mean


def make_latent_value(
    latent_dim: int, num_cells: Sequence[int] = (1024, 1024), latent_key=LATENT_KEY
) -> ValueOperator:
    """:math:`V(z)`: an MLP on the latent state (Table 11: 1024×1024, ReLU)."""
    net = MLP(in_features=latent_dim, out_features=1, num_cells=list(num_cells), activation_class=nn.ReLU)
    return ValueOperator(net, in_keys=[latent_key], out_keys=["state_value"])


def make_guide_policy(
    latent_dim: int,
    mode: str = "deterministic",
    num_cells: Sequence[int] = (1024, 1024),
    *,
    latent_key=LATENT_KEY,
    out_key=GUIDE_KEY,
    min_scale: float = 1e-3,
) -> TensorDictModule | ProbabilisticTensorDictSequential:
    r"""The guide policy :math:`\pi_g`, proposing the next latent state (Table 11: 1024×1024, ReLU).

    ``mode="deterministic"`` gives :math:`\pi_g(z_s)` of Eq. (9);
    ``mode="stochastic"`` gives a Gaussian :math:`\pi_g(z_{s'} | z_s)` of Eq. (10)
    whose deterministic sample is its mean.
    """
    if mode == "deterministic":
        net = MLP(in_features=latent_dim, out_features=latent_dim, num_cells=list(num_cells), activation_class=nn.ReLU)
        return TensorDictModule(net, in_keys=[latent_key], out_keys=[out_key])
    if mode == "stochastic":
        net = nn.Sequential(
            MLP(in_features=latent_dim, out_features=2 * latent_dim, num_cells=list(num_cells), activation_class=nn.ReLU),
            NormalParamExtractor(scale_mapping=f"biased_softplus_1.0_{min_scale}"),
        )
        params = TensorDictModule(net, in_keys=[latent_key], out_keys=["loc", "scale"])
        dist = ProbabilisticTensorDictModule(
            in_keys=["loc", "scale"],
            out_keys=[out_key],
            distribution_class=IndependentNormal,
            default_interaction_type=ExplorationType.DETERMINISTIC,
        )
        return ProbabilisticTensorDictSequential(params, dist)
    raise ValueError(f"guide mode must be 'deterministic' or 'stochastic', got {mode!r}.")


class _FrozenTSIDMPart(nn.Module):
    """Holds a trained TS-IDM for inference: eval mode (no dropout) and no gradients, always."""

    def __init__(self, tsidm: TSIDM) -> None:
        super().__init__()
        if not isinstance(tsidm, TSIDM):
            raise TypeError(f"expected a TSIDM, got {type(tsidm).__name__}.")
        self.tsidm = tsidm.eval()

    def train(self, mode: bool = True):
        # Putting a policy in train mode must not turn h_inv's dropout back on.
        super().train(mode)
        self.tsidm.eval()
        return self


class StateEncoder(_FrozenTSIDMPart):
    r""":math:`z_s = \phi_s(s)` from a raw observation, normalization included."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.tsidm.encode_state(observation)


class LatentActionHead(_FrozenTSIDMPart):
    r"""Eq. (11): :math:`a^* = \psi_a(h_{inv}(z_s, z_{s'}^*))`, clipped to the action bounds.

    No training is needed: both networks come from the trained TS-IDM.

    Two readings the paper leaves open, off by default (README, "Deviations from the paper"):
    ``reencode_proposal`` feeds :math:`\phi_s(\psi_s(z_{s'}^*))` to
    :math:`h_{inv}` instead of the guide's output itself, and
    ``inverse_dropout`` keeps :math:`h_{inv}`'s training dropout on when acting.
    """

    def __init__(
        self,
        tsidm: TSIDM,
        low: torch.Tensor | float | None = None,
        high: torch.Tensor | float | None = None,
        *,
        reencode_proposal: bool = False,
        inverse_dropout: bool = False,
    ):
        super().__init__(tsidm)
        self.register_buffer("low", None if low is None else torch.as_tensor(low, dtype=torch.float32))
        self.register_buffer("high", None if high is None else torch.as_tensor(high, dtype=torch.float32))
        self.reencode_proposal = bool(reencode_proposal)
        self.inverse_dropout = bool(inverse_dropout)

    def latent_action(self, latent_state: torch.Tensor, next_latent_state: torch.Tensor) -> torch.Tensor:
        r""":math:`z_a = h_{inv}(z_s, z_{s'}^*)`, with the proposal re-encoded and h_inv's dropout as configured."""
        if self.reencode_proposal:
            next_latent_state = self.tsidm.embed_state(self.tsidm.decode_state(next_latent_state))
        self.tsidm.inverse_dynamics.train(self.inverse_dropout)
        try:
            return self.tsidm.infer_latent_action(latent_state, next_latent_state)
        finally:
            self.tsidm.inverse_dynamics.eval()

    def action(self, latent_action: torch.Tensor) -> torch.Tensor:
        r""":math:`\psi_a(z_a)`, clipped to the action bounds."""
        action = self.tsidm.decode_action(latent_action)
        if self.low is not None or self.high is not None:
            action = action.clamp(self.low, self.high)
        return action

    def forward(self, latent_state: torch.Tensor, next_latent_state: torch.Tensor) -> torch.Tensor:
        # Eq. (11)
        return self.action(self.latent_action(latent_state, next_latent_state))


def make_tels_actor(
    tsidm: TSIDM,
    guide_policy: TensorDictModule,
    action_spec=None,
    *,
    from_latent: bool = False,
    observation_key="observation",
    latent_key=LATENT_KEY,
    guide_key=GUIDE_KEY,
    action_key="action",
    reencode_proposal: bool = False,
    inverse_dropout: bool = False,
) -> TensorDictSequential:
    r"""The TELS policy: observation → :math:`z_s` → :math:`\pi_g` → :math:`z_{s'}^*` → Eq. (11) → action.

    Args:
        tsidm: the trained TS-IDM.
        guide_policy: the guide, as made by :func:`make_guide_policy`.
        action_spec: a bounded action spec (e.g. ``env.action_spec``); actions are clipped to it.
        from_latent: if ``True`` the chain starts from ``latent_key``, for use
            behind a :class:`~torchrl_tels.envs.TSIDMEncoderTransform`;
            otherwise it starts from the raw observation and encodes it itself.
        reencode_proposal, inverse_dropout: see :class:`LatentActionHead` (off: Eq. 11 as written).
    """
    low = high = None
    if action_spec is not None:
        low, high = getattr(action_spec, "low", None), getattr(action_spec, "high", None)
    head = TensorDictModule(
        LatentActionHead(tsidm, low, high, reencode_proposal=reencode_proposal, inverse_dropout=inverse_dropout),
        in_keys=[latent_key, guide_key],
        out_keys=[action_key],
    )
    modules = [guide_policy, head]
    if not from_latent:
        encoder = TensorDictModule(StateEncoder(tsidm), in_keys=[observation_key], out_keys=[latent_key])
        modules.insert(0, encoder)
    return TensorDictSequential(*modules)


POLICY_FORMAT = "torchrl_tels.policy/v1"


def save_guide_policy(
    path,
    guide_policy: TensorDictModule,
    *,
    latent_dim: int,
    mode: str,
    num_cells: Sequence[int],
    actor_options: dict | None = None,
    metadata: dict | None = None,
) -> None:
    """Writes the trained guide π_g (and how to rebuild it) atomically; pair it with the run's ``tsidm.pt``.

    ``actor_options`` (:func:`make_tels_actor`'s ``reencode_proposal`` and
    ``inverse_dropout``) are stored so :func:`load_tels_actor` acts the same way.
    """
    from torchrl_tels.checkpoint import atomic_save

    atomic_save(
        {
            "format": POLICY_FORMAT,
            "latent_dim": int(latent_dim),
            "mode": mode,
            "num_cells": [int(c) for c in num_cells],
            "actor_options": {k: bool(v) for k, v in (actor_options or {}).items()},
            "state_dict": {k: v.detach().cpu() for k, v in guide_policy.state_dict().items()},
            "metadata": dict(metadata or {}),
        },
        path,
    )


def load_tels_actor(
    policy_path,
    tsidm: TSIDM | str,
    action_spec=None,
    *,
    from_latent: bool = False,
    **actor_kwargs,
) -> TensorDictSequential:
    """Rebuilds the Eq. (11) actor from a run's ``policy.pt`` and its TS-IDM (a module or ``tsidm.pt``).

    ``actor_kwargs`` go to :func:`make_tels_actor` (``reencode_proposal``, ``inverse_dropout``);
    they override the options the policy was saved with.
    """
    from torchrl_tels.checkpoint import CheckpointError, load_checkpoint

    if not isinstance(tsidm, TSIDM):
        tsidm = TSIDM.load(tsidm)
    payload = load_checkpoint(policy_path, POLICY_FORMAT)
    if payload["latent_dim"] != tsidm.latent_state_dim:
        raise CheckpointError(
            f"guide policy {policy_path} works in a {payload['latent_dim']}-dim latent space, "
            f"but the TS-IDM's latent state has {tsidm.latent_state_dim} dims: they come from different runs."
        )
    guide = make_guide_policy(payload["latent_dim"], payload["mode"], payload["num_cells"])
    try:
        guide.load_state_dict(payload["state_dict"])
    except RuntimeError as err:
        raise CheckpointError(f"guide policy {policy_path} does not match its own config: {err}") from None
    options = {**payload.get("actor_options", {}), **actor_kwargs}
    return make_tels_actor(tsidm, guide, action_spec, from_latent=from_latent, **options)
