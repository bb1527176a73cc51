"""TS-IDM training objective, paper Eq. (3)-(7)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from torchrl_tels.modules.tsidm import jvp, LATENT_STD_EPS, squared_norm, standardize, TSIDM
from torchrl_tels.objectives._common import checked_get, LazyInKeysMixin, SelectableOutKeysMixin

__all__ = ["TSIDMLoss", "TSIDM_ABLATIONS", "LATENT_SCALES"]

#: Table 3's variants, in the order the paper adds the terms.
TSIDM_ABLATIONS = ("ae", "dyn", "ode", "full")
#: How the latent scale is fixed: ``free`` (Eq. 7 as written), ``relative`` (the
#: latent-space terms over the batch's latent step) or ``standardized`` (a
#: fixed-scale φ_s, see ``TSIDM(latent_standardization=True)``).
LATENT_SCALES = ("free", "relative", "standardized")


class TSIDMLoss(SelectableOutKeysMixin, LazyInKeysMixin, LossModule):
    r"""The TS-IDM objective of TELS (paper §3.1, Eq. 7).

    With :math:`s, s'` normalized by the TS-IDM and :math:`\dot s = s' - s`,
    :math:`z_s = \phi_s(s)`, :math:`z_{s'} = \phi_s(s')`,
    :math:`z_a = h_{inv}(z_s, z_{s'})`:

    .. math::

        \ell_{rec} &= \|\psi_s(z_s) - s\|^2 + \|\psi_a(z_a) - a\|^2 && (3)\\
        \ell_{dyn} &= \|\nabla_s\phi_s(s)\,\dot s - h_{fwd}(z_s, z_a)\|^2
                    + \|\nabla_{s'}\phi_s(s')(-\dot s) - h_{rvs}(z_{s'}, z_a)\|^2 && (4)\\
        \ell_{ode} &= \|\nabla_{z_s}\psi_s(z_s)\,h_{fwd}(z_s, z_a) - \dot s\|^2
                    + \|\nabla_{z_{s'}}\psi_s(z_{s'})\,h_{rvs}(z_{s'}, z_a) + \dot s\|^2 && (5)\\
        \ell_{T\text{-}sym} &= \|h_{fwd}(z_s, z_a) + h_{rvs}(z_s + h_{fwd}(z_s, z_a), z_a)\|^2 && (6)\\
        \mathcal{L} &= \ell_{rec} + \beta(\ell_{dyn} + \ell_{ode} + \ell_{T\text{-}sym}) && (7)

    ``term_weights`` generalizes Eq. (7) to
    :math:`\ell_{rec} + \beta(w_{dyn}\ell_{dyn} + w_{ode}\ell_{ode} + w_{T\text{-}sym}\ell_{T\text{-}sym})`;
    the paper's weights are all 1. TSRL's code (Cheng et al., 2023), which TS-IDM
    descends from, weighs the dynamics and consistency terms 0.1 and the decoder-ODE term 1.

    **Latent scale.** Eq. (7) has an exact symmetry: for any :math:`c > 0`,
    :math:`\phi_s \to c\phi_s`, :math:`\psi_s(z) \to \psi_s(z/c)`,
    :math:`h_{inv}(z, z') \to h_{inv}(z/c, z'/c)` and
    :math:`h_{fwd}, h_{rvs} \to c\,h(z/c, z_a)` leave :math:`\ell_{rec}` and
    :math:`\ell_{ode}` unchanged and multiply :math:`\ell_{dyn}` and
    :math:`\ell_{T\text{-}sym}` by :math:`c^2`. Gradient descent can therefore
    lower those two terms by shrinking the latent space instead of learning
    dynamics. Two options remove the direction:

    * a TS-IDM built with ``latent_standardization=True``: the loss
      standardizes :math:`\phi_s`'s output with the batch's mean and standard
      deviation (gradient through both, as batch normalization does), so every
      term is exactly invariant and the scale carries no gradient;
    * ``relative=True``: :math:`\ell_{dyn}` and :math:`\ell_{T\text{-}sym}` are
      divided by the batch's mean latent step
      :math:`\bar d = \frac1B\sum_i\|z_{s'_i} - z_{s_i}\|^2` (gradient through
      :math:`\bar d`), which scales as :math:`c^2` too.

    The four Jacobian-vector products are computed with forward-mode AD
    (:func:`torchrl_tels.modules.tsidm.jvp`), never by building Jacobians.
    Eq. (7) sums over the dataset; here it is averaged over the batch, which
    only rescales the learning rate.

    The output holds ``loss_state_rec``, ``loss_action_rec`` (:math:`\ell_{rec}`
    has weight 1, Table 10) and ``loss_dyn``, ``loss_ode``, ``loss_tsym``
    already multiplied by the one shared :math:`\beta` (Appendix B.5) and their
    term weight, so that the sum of the ``loss_*`` entries is exactly Eq. (7). Unweighted, detached
    copies ride along as ``ell_rec``, ``ell_dyn``, ``ell_ode``, ``ell_tsym``,
    ``ell_total`` (= Eq. 7) and ``ell_sum`` (the terms summed without β).
    Appendix B.5 picks β as the one "with the lowest TS-IDM training loss";
    ``ell_total`` scales three of its terms by the candidate β itself and so
    leans toward the smallest one, while ``ell_sum`` compares candidates on one
    objective (``study/LOG.md``, "the β rule read two ways").

    ``select_out_keys`` keeps a subset of these entries (``out_keys_source``
    still lists them all); the objective is then the sum of the ``loss_*``
    entries kept, e.g. ``loss_state_rec`` + ``loss_action_rec`` to train the
    autoencoder part alone.

    Args:
        tsidm: the :class:`~torchrl_tels.modules.TSIDM` to train.
        beta: the shared weight β of Eq. (7) (Table 10: chosen from {0.01, 0.1, 1}).
        ablation: one of Table 3's variants: ``"ae"`` (φ/ψ + h_inv: ℓ_rec only),
            ``"dyn"`` (+ h_fwd, h_rvs: + ℓ_dyn), ``"ode"`` (+ ℓ_ode) or ``"full"`` (+ ℓ_T-sym).
        dim_reduction: how :math:`\|\cdot\|^2` reduces over vector entries,
            ``"sum"`` (as written, default) or ``"mean"``.
        term_weights: per-term weights :math:`w` inside β's bracket, a mapping with any of
            ``"dyn"``, ``"ode"``, ``"tsym"`` (missing ones are 1). Default: all 1 (Eq. 7).
        relative: divide :math:`\ell_{dyn}` and :math:`\ell_{T\text{-}sym}` by the
            batch's mean latent step :math:`\bar d` (see "Latent scale"). Default ``False``.
        check_inputs: validate keys, shapes and finiteness of every batch.

    Examples:
        >>> tsidm = TSIDM(11, 3)
        >>> loss = TSIDMLoss(tsidm, beta=1.0)
        >>> td = TensorDict({"observation": torch.randn(8, 11), "action": torch.randn(8, 3),
        ...                  ("next", "observation"): torch.randn(8, 11)}, [8])
        >>> out = loss(td)
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> _ = loss.select_out_keys("loss_state_rec", "loss_action_rec")
        >>> state_rec, action_rec = loss(observation=td["observation"], action=td["action"],
        ...                              next_observation=td["next", "observation"])
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`TSIDMLoss`, configurable with ``set_keys``.

        Attributes:
            observation (NestedKey): the raw state :math:`s`; :math:`s'` is read
                from ``("next", observation)`` of the same transition.
                Defaults to ``"observation"``.
            action (NestedKey): the action :math:`a`. Defaults to ``"action"``.
            terminated (NestedKey): accepted for symmetry with the value
                losses; Eq. (3)-(7) do not depend on it, since :math:`s'` is
                always the transition's own next state. Defaults to ``"terminated"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    # The Jacobian-vector product used by Eqs. (4)-(5); a seam for the
    # vmap(jacrev) comparison in benchmarks/tsidm_step.py.
    jvp = staticmethod(jvp)

    tsidm: TSIDM
    tsidm_params: TensorDictParams
    target_tsidm_params: TensorDictParams

    def __init__(
        self,
        tsidm: TSIDM,
        *,
        beta: float = 1.0,
        ablation: str = "full",
        dim_reduction: str = "sum",
        term_weights: dict[str, float] | None = None,
        relative: bool = False,
        check_inputs: bool = True,
    ) -> None:
        self._in_keys = None
        super().__init__()
        if not isinstance(tsidm, TSIDM):
            raise TypeError(f"TSIDMLoss expects a TSIDM, got {type(tsidm).__name__}.")
        beta = float(beta)
        if not math.isfinite(beta) or beta < 0:
            raise ValueError(f"TSIDMLoss: beta must be a finite number >= 0, got {beta}.")
        if ablation not in TSIDM_ABLATIONS:
            raise ValueError(
                f"TSIDMLoss: unknown ablation {ablation!r}; choose one of {TSIDM_ABLATIONS}."
            )
        if dim_reduction not in ("sum", "mean"):
            raise ValueError(
                f"TSIDMLoss: dim_reduction must be 'sum' or 'mean', got {dim_reduction!r}."
            )
        term_weights = dict(term_weights or {})
        unknown = set(term_weights) - {"dyn", "ode", "tsym"}
        if unknown:
            raise ValueError(f"TSIDMLoss: unknown term_weights {sorted(unknown)}; use 'dyn', 'ode', 'tsym'.")
        for name, weight in term_weights.items():
            if not math.isfinite(float(weight)) or float(weight) < 0:
                raise ValueError(f"TSIDMLoss: term_weights[{name!r}] must be finite and >= 0, got {weight}.")
        self.term_weights = {name: float(term_weights.get(name, 1.0)) for name in ("dyn", "ode", "tsym")}
        self.beta = beta
        self.ablation = ablation
        self.dim_reduction = dim_reduction
        self.relative = bool(relative)
        self.check_inputs = check_inputs
        self.convert_to_functional(tsidm, "tsidm", create_target_params=False)

    # keys ----------------------------------------------------------------
    def _set_in_keys(self):
        self._in_keys = [
            self.tensor_keys.observation,
            self.tensor_keys.action,
            ("next", self.tensor_keys.observation),
        ]

    def _all_out_keys(self):
        level = TSIDM_ABLATIONS.index(self.ablation)
        terms = ["loss_state_rec", "loss_action_rec", "loss_dyn", "loss_ode", "loss_tsym"]
        ells = ["ell_rec", "ell_dyn", "ell_ode", "ell_tsym"]
        return terms[: 2 + level] + ells[: 1 + level] + ["ell_total", "ell_sum", "latent_rms", "latent_step_rms"]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._set_in_keys()

    # terms ----------------------------------------------------------------
    def _read_batch(self, tensordict: TensorDictBase):
        obs_dim, act_dim = self.tsidm.observation_dim, self.tsidm.action_dim
        keys = self.tensor_keys
        if self.check_inputs:
            get = lambda key, dim: checked_get(tensordict, key, dim, type(self).__name__)
        else:
            get = lambda key, dim: tensordict.get(key)
        observation = get(keys.observation, obs_dim)
        next_observation = get(("next", keys.observation), obs_dim)
        action = get(keys.action, act_dim)
        return observation, action, next_observation

    @staticmethod
    def _standardize(latent: torch.Tensor, tangent: torch.Tensor | None):
        # Batch statistics with their gradient: the encoder's output scale then
        # cancels exactly and carries no gradient. The JVP is per sample, with
        # the statistics held fixed, as φ_s acts once they are frozen.
        loc = latent.mean(0)
        scale = latent.var(0, unbiased=True).add(LATENT_STD_EPS**2).sqrt()
        latent = standardize(latent, loc, scale)
        return latent, None if tangent is None else tangent / scale

    def _reduce(self, per_sample: torch.Tensor) -> torch.Tensor:
        return per_sample.mean()

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation, action, next_observation = self._read_batch(tensordict)
        level = TSIDM_ABLATIONS.index(self.ablation)
        sq = lambda x: squared_norm(x, self.dim_reduction)
        with self.tsidm_params.to_module(self.tsidm, preserve_module_state=False):
            tsidm = self.tsidm
            s = tsidm.normalize_state(observation)
            s_next = tsidm.normalize_state(next_observation)
            s_dot = s_next - s

            # One batched pass encodes s and s' and, for ℓ_dyn, pushes the
            # tangents ṡ and -ṡ through φ_s at the same time.
            states = torch.cat([s, s_next], 0)
            if level >= 1:
                z_both, encoder_jvp = self.jvp(tsidm.state_encoder, states, torch.cat([s_dot, -s_dot], 0))
            else:
                z_both, encoder_jvp = tsidm.state_encoder(states), None
            if tsidm.latent_standardization:
                z_both, encoder_jvp = self._standardize(z_both, encoder_jvp)
            if level >= 1:
                jvp_s, jvp_s_next = encoder_jvp.split(s.shape[0], 0)
            z, z_next = z_both.split(s.shape[0], 0)
            # d̄: the batch's mean squared latent step, the scale of ℓ_dyn and ℓ_T-sym
            latent_step = sq(z_next - z).mean()
            z_a = tsidm.infer_latent_action(z, z_next)

            # per-sample regularizers of Eq. (7), in Table 3's order
            regularizers = {}
            if level >= 1:
                z_dot_fwd = tsidm.latent_forward(z, z_a)
                z_dot_rvs = tsidm.latent_reverse(z_next, z_a)
                # Eq. (4)
                regularizers["dyn"] = sq(jvp_s - z_dot_fwd) + sq(jvp_s_next - z_dot_rvs)
            if level >= 2:
                s_hat, decoder_jvp = self.jvp(
                    tsidm.state_decoder, z_both, torch.cat([z_dot_fwd, z_dot_rvs], 0)
                )
                s_hat = s_hat[: s.shape[0]]
                jvp_fwd, jvp_rvs = decoder_jvp.split(s.shape[0], 0)
                # Eq. (5)
                regularizers["ode"] = sq(jvp_fwd - s_dot) + sq(jvp_rvs + s_dot)
            else:
                s_hat = tsidm.decode_state(z)
            if level >= 3:
                # Eq. (6)
                regularizers["tsym"] = tsidm.tsym_consistency(z, z_a, self.dim_reduction)
            # Eq. (3)
            state_rec = sq(s_hat - s)
            action_rec = sq(tsidm.decode_action(z_a) - action)

        out = {
            "loss_state_rec": self._reduce(state_rec),
            "loss_action_rec": self._reduce(action_rec),
        }
        ell_rec = (out["loss_state_rec"] + out["loss_action_rec"]).detach()
        ells = {"ell_rec": ell_rec}
        ell_total = ell_sum = ell_rec
        for name, per_sample in regularizers.items():
            value = self._reduce(per_sample)
            if self.relative and name in ("dyn", "tsym"):
                value = value / latent_step.clamp_min(LATENT_STD_EPS**2)
            weight = self.beta * self.term_weights[name]
            out[f"loss_{name}"] = weight * value
            ells[f"ell_{name}"] = value.detach()
            ell_total = ell_total + weight * value.detach()
            ell_sum = ell_sum + value.detach()
        # Eq. (7)
        ells["ell_total"] = ell_total
        ells["ell_sum"] = ell_sum
        out.update(ells)
        # the latent scale the symmetry would shrink: RMS spread per dimension and RMS step
        out["latent_rms"] = z_both.detach().var(0).mean().sqrt()
        out["latent_step_rms"] = latent_step.detach().sqrt()
        return self._selected_output(TensorDict(out, batch_size=[]))
