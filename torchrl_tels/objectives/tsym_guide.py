"""T-symmetry regularized guide-policy optimization, paper Eq. (9) and (10)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import ValueEstimators

from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY
from torchrl_tels.modules.tsidm import squared_norm, TSIDM
from torchrl_tels.objectives._common import (
    checked_get, GAMMA_IN_CONSTRUCTOR, LazyInKeysMixin, make_td0_value_estimator, SelectableOutKeysMixin,
)

__all__ = ["TSymGuideLoss", "value_scale"]

GUIDE_MODES = ("deterministic", "stochastic")


def effective_sample_fraction(weight: torch.Tensor) -> torch.Tensor:
    r"""Kish's effective sample size of weights over their count, :math:`(\sum w)^2 / (n \sum w^2)`:
    1 when every sample weighs the same, :math:`1/n` when one sample carries all the weight."""
    weight = weight.detach().reshape(-1)
    return weight.sum().square() / (weight.numel() * weight.square().sum()).clamp_min(1e-30)


def value_scale(alpha: float, data_values: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    r""":math:`\lambda_\alpha = \alpha / [\sum_i |V(\phi_s(s_i))| / N]` over the batch (Appendix C.3)."""
    return alpha / data_values.abs().mean().clamp_min(eps)


class TSymGuideLoss(SelectableOutKeysMixin, LazyInKeysMixin, LossModule):
    r"""Trains the guide policy :math:`\pi_g` in the TS-IDM latent space (paper §3.2).

    Deterministic guide, Eq. (9) (MuJoCo):

    .. math::

        \max_{\pi_g} \mathbb{E}\big[\lambda_\alpha V(\pi_g(z_s))
            - \eta \|\psi_s(\pi_g(z_s)) - s'\|^2
            - \ell_{T\text{-}sym}(z_s, h_{inv}(z_s, \pi_g(z_s)))\big],
        \quad \lambda_\alpha = \frac{\alpha}{\frac1N\sum_i |V(z_{s_i})|}

    with :math:`s'` in the TS-IDM's normalized state space. Output:
    ``loss_guide_value`` (:math:`-\lambda_\alpha V`), ``loss_guide_state``
    (the η term) and ``loss_tsym``.

    Optionally (``reach_weight`` :math:`w_r > 0`, not in the paper) a reachability term asks that
    the TS-IDM's own forward model reach the proposal from :math:`z_s` with the latent action
    that Eq. (11) will use:

    .. math::

        \ell_{reach} = w_r\,\frac{\mathbb E\|z_s + h_{fwd}(z_s, h_{inv}(z_s, \pi_g(z_s))) - \pi_g(z_s)\|^2}
            {\mathbb E\|z_{s'} - z_s\|^2}

    (``loss_reach``; the denominator is the batch's data step, detached, so the term is a relative
    error whatever the latent scale). Eq. (6) checks only that the forward and reverse models agree
    about the latent action; it does not check that the action leads to the proposed state, and
    proposals that the environment does not reach can satisfy it as well as the data's transitions.

    Stochastic guide, Eq. (10) (AntMaze):

    .. math::

        \max_{\pi_g} \mathbb{E}\big[\exp(\alpha A(z_s, z_{s'})) \log \pi_g(z_{s'}|z_s)
            - \ell_{T\text{-}sym}(z_s, h_{inv}(z_s, \tilde z)))\big],
        \quad \tilde z \sim \pi_g(\cdot|z_s)

    with :math:`A = r + \gamma(1-d) V(z_{s'}) - V(z_s)` computed by TorchRL's TD(0)
    estimator (set γ with ``make_value_estimator(gamma=...)``). The weight
    :math:`\exp(\alpha A)` is clipped at ``max_weight`` (100 by default, as
    in IQL/POR) so that one large advantage cannot dominate a batch. The
    sample :math:`\tilde z` is drawn with ``rsample`` (reparameterized), so
    :math:`\ell_{T\text{-}sym}` differentiates through it even though TorchRL
    losses run in deterministic exploration mode. Output: ``loss_guide_awr``
    and ``loss_tsym``.

    :math:`\ell_{T\text{-}sym}` is Eq. (6) of the trained TS-IDM
    (:meth:`TSIDM.tsym_consistency`). The TS-IDM and :math:`V` are frozen here:
    their weights are held as detached views (they follow updates made by
    :class:`LatentExpectileLoss`) and only the guide's parameters are
    parameters of this loss.

    ``out_keys`` follow ``mode``, ``tsym_regularizer`` and ``reach_weight``;
    ``select_out_keys`` keeps a subset of them (``out_keys_source`` still lists
    them all) and the objective is then the sum of the ``loss_*`` entries kept.

    Args:
        guide_network: :func:`~torchrl_tels.modules.make_guide_policy` output
            (a ``TensorDictModule`` for ``"deterministic"``, a probabilistic
            sequence for ``"stochastic"``).
        value_network: the latent value :math:`V` (reads the latent key, writes ``"state_value"``).
        tsidm: the trained TS-IDM.
        mode: ``"deterministic"`` (Eq. 9) or ``"stochastic"`` (Eq. 10).
        alpha: α (Table 11: 0.01 MuJoCo, 10 AntMaze).
        eta: η of Eq. (9) (Appendix B.5: from {1, 5, 10}).
        tsym_regularizer: ``False`` drops :math:`\ell_{T\text{-}sym}` (Fig. 5 ablation).
        tsym_weight: weight :math:`w` of the guide's :math:`\ell_{T\text{-}sym}` term,
            ``loss_tsym`` = :math:`w\,\frac1B\sum_i \ell_{T\text{-}sym,i} / d_{ref}`
            (mean over the batch, :math:`\|\cdot\|^2` reduced by ``dim_reduction``).
            The paper's Eq. (9)/(10) have :math:`w = 1`, :math:`d_{ref} = 1`.
        tsym_reference: :math:`d_{ref}`, the data's mean squared latent step
            :math:`\mathbb E\|z_{s'} - z_s\|^2`. Eq. (6) scales as the square of
            the latent scale while the state term of Eq. (9) does not; dividing
            by :math:`d_{ref}` makes ``loss_tsym`` a relative error whatever the
            latent scale. ``None`` (default) keeps Eq. (9)/(10) as written.
        reach_weight: :math:`w_r` of ``loss_reach`` (deterministic guide only); 0 (default) leaves Eq. (9) as written.
        max_weight: clip of the AWR weight.
        dim_reduction: ``"sum"`` (as written) or ``"mean"`` over vector entries of each norm.
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`TSymGuideLoss`.

        Attributes:
            latent (NestedKey): :math:`z_s`, and ``("next", latent)`` for :math:`z_{s'}`.
                Defaults to ``"latent"``.
            observation (NestedKey): raw state; ``("next", observation)`` is the
                :math:`s'` of Eq. (9). Defaults to ``"observation"``.
            guide (NestedKey): where the guide writes its proposal. Defaults to ``"guide_latent"``.
            value (NestedKey): where :math:`V` writes. Defaults to ``"state_value"``.
            value_target (NestedKey): TD target key of the estimator. Defaults to ``"value_target"``.
            reward, done, terminated (NestedKey): read under ``"next"`` (Eq. 10 only).
        """

        latent: NestedKey = LATENT_KEY
        observation: NestedKey = "observation"
        guide: NestedKey = GUIDE_KEY
        value: NestedKey = "state_value"
        value_target: NestedKey = "value_target"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0

    guide_network: TensorDictModule
    guide_network_params: TensorDictParams
    target_guide_network_params: TensorDictParams

    def __init__(
        self,
        guide_network: TensorDictModule,
        value_network: TensorDictModule,
        tsidm: TSIDM,
        *,
        mode: str = "deterministic",
        alpha: float = 0.01,
        eta: float = 1.0,
        tsym_regularizer: bool = True,
        tsym_weight: float = 1.0,
        tsym_reference: float | None = None,
        reach_weight: float = 0.0,
        max_weight: float = 100.0,
        dim_reduction: str = "sum",
        gamma: float | None = None,
        check_inputs: bool = True,
    ) -> None:
        self._in_keys = None
        super().__init__()
        if gamma is not None:
            raise TypeError(GAMMA_IN_CONSTRUCTOR)
        if mode not in GUIDE_MODES:
            raise ValueError(f"TSymGuideLoss: mode must be one of {GUIDE_MODES}, got {mode!r}.")
        checks = [("alpha", alpha, 0.0), ("eta", eta, 0.0), ("max_weight", max_weight, 1e-12),
                  ("tsym_weight", tsym_weight, 0.0), ("reach_weight", reach_weight, 0.0)]
        if tsym_reference is not None:
            checks.append(("tsym_reference", tsym_reference, 1e-12))
        for name, value, low in checks:
            if not (math.isfinite(float(value)) and float(value) >= low):
                raise ValueError(f"TSymGuideLoss: {name} must be a finite number >= {low}, got {value}.")
        if not isinstance(tsidm, TSIDM):
            raise TypeError(f"TSymGuideLoss expects a TSIDM, got {type(tsidm).__name__}.")
        squared_norm(torch.zeros(1), dim_reduction)  # validates the name
        self.mode = mode
        self.alpha = float(alpha)
        self.eta = float(eta)
        self.tsym_regularizer = bool(tsym_regularizer)
        self.tsym_weight = float(tsym_weight)
        self.tsym_reference = None if tsym_reference is None else float(tsym_reference)
        if reach_weight and mode != "deterministic":
            raise ValueError("TSymGuideLoss: reach_weight applies to the deterministic guide of Eq. (9) only.")
        self.reach_weight = float(reach_weight)
        self.max_weight = float(max_weight)
        self.dim_reduction = dim_reduction
        self.check_inputs = check_inputs

        self.convert_to_functional(guide_network, "guide_network", create_target_params=False)
        self._register_frozen(value_network, "value_network")
        self._register_frozen(tsidm.eval(), "tsidm")

    def _register_frozen(self, module: torch.nn.Module, name: str) -> None:
        # Detached views share storage with the live weights, so the guide
        # always sees the current V, but no gradient or optimizer built from
        # this loss's parameters() can reach V or the TS-IDM.
        frozen = TensorDictParams(TensorDict.from_module(module).data, no_convert=True)
        setattr(self, f"{name}_params", frozen)
        self.__dict__[name] = module

    # keys -----------------------------------------------------------------
    def _set_in_keys(self):
        keys = self.tensor_keys
        in_keys = [keys.latent]
        if self.mode == "deterministic":
            in_keys.append(("next", keys.observation))
            if self.reach_weight:
                in_keys.append(("next", keys.latent))
        else:
            in_keys += [
                ("next", keys.latent),
                ("next", keys.reward),
                ("next", keys.done),
                ("next", keys.terminated),
            ]
        self._in_keys = in_keys

    def _all_out_keys(self):
        if self.mode == "deterministic":
            keys = ["loss_guide_value", "loss_guide_state"] + (["loss_reach"] if self.reach_weight else [])
            extra = ["lambda_alpha", "guide_value", "guide_step_rms"]
            if self.tsym_regularizer:
                extra.append("tsym_to_state_ratio")
        else:
            keys = ["loss_guide_awr"]
            extra = ["advantage", "clipped_weight_fraction", "effective_sample_fraction"]
        return keys + (["loss_tsym"] if self.tsym_regularizer else []) + extra

    # pieces ----------------------------------------------------------------
    def _value(self, latent: torch.Tensor) -> torch.Tensor:
        td = TensorDict({self.value_network.in_keys[0]: latent}, batch_size=latent.shape[:-1])
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            self.value_network(td)
        return td.get(self.tensor_keys.value).squeeze(-1)

    def tsym_loss(self, latent: torch.Tensor, proposed_next_latent: torch.Tensor) -> torch.Tensor:
        r"""The guide's regularizer, :math:`w\,\mathbb E[\ell_{T\text{-}sym}(z_s, h_{inv}(z_s, z'))] / d_{ref}`.

        Eq. (6) applied to the proposed transition; call inside the frozen TS-IDM's parameters.
        """
        tsidm = self.tsidm
        latent_action = tsidm.infer_latent_action(latent, proposed_next_latent)
        value = tsidm.tsym_consistency(latent, latent_action, self.dim_reduction).mean()
        if self.tsym_reference is not None:
            value = value / self.tsym_reference
        return self.tsym_weight * value

    def reach_loss(self, latent: torch.Tensor, proposed_next_latent: torch.Tensor,
                   next_latent: torch.Tensor) -> torch.Tensor:
        r""":math:`\ell_{reach}`: the forward model's miss of the proposal over the data's latent step
        (``next_latent``: the batch's :math:`z_{s'}`); call inside the frozen TS-IDM's parameters."""
        tsidm = self.tsidm
        reached = latent + tsidm.latent_forward(latent, tsidm.infer_latent_action(latent, proposed_next_latent))
        miss = squared_norm(reached - proposed_next_latent, self.dim_reduction).mean()
        data_step = squared_norm(next_latent - latent, self.dim_reduction).mean().detach().clamp_min(1e-12)
        return self.reach_weight * miss / data_step

    def _check(self, tensordict: TensorDictBase) -> torch.Tensor:
        owner = type(self).__name__
        latent_dim = self.tsidm.latent_state_dim
        for key in self.in_keys:
            if key == self.tensor_keys.latent or key == ("next", self.tensor_keys.latent):
                dim = latent_dim
            elif key == ("next", self.tensor_keys.observation):
                dim = self.tsidm.observation_dim
            else:
                dim = None
            checked_get(tensordict, key, dim, owner)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.check_inputs:
            self._check(tensordict)
        if self.mode == "deterministic":
            out = self.deterministic_loss(tensordict)
        else:
            out = self.stochastic_loss(tensordict)
        return self._selected_output(out)

    def deterministic_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        r"""Eq. (9) as losses: ``loss_guide_value`` (:math:`-\lambda_\alpha V(\pi_g(z_s))`),
        ``loss_guide_state`` (the η term), ``loss_tsym`` and, with ``reach_weight``, ``loss_reach``,
        with detached diagnostics."""
        keys = self.tensor_keys
        latent = tensordict.get(keys.latent)
        td = tensordict.select(*self.guide_network.in_keys, strict=False)
        with self.guide_network_params.to_module(self.guide_network, preserve_module_state=False):
            self.guide_network(td)
        proposal = td.get(keys.guide)
        with torch.no_grad():
            lambda_alpha = value_scale(self.alpha, self._value(latent))
        with self.tsidm_params.to_module(self.tsidm, preserve_module_state=False):
            next_state = self.tsidm.normalize_state(tensordict.get(("next", keys.observation)))
            guide_value = self._value(proposal)
            # Eq. (9), as a loss to minimize
            out = {
                "loss_guide_value": -(lambda_alpha * guide_value).mean(),
                "loss_guide_state": self.eta
                * squared_norm(self.tsidm.decode_state(proposal) - next_state, self.dim_reduction).mean(),
            }
            if self.reach_weight:
                out["loss_reach"] = self.reach_loss(latent, proposal, tensordict.get(("next", keys.latent)))
            if self.tsym_regularizer:
                out["loss_tsym"] = self.tsym_loss(latent, proposal)
        out["lambda_alpha"] = lambda_alpha
        out["guide_value"] = guide_value.detach().mean()
        # whether T-symmetry does anything: its share of the state term, and the proposed step size
        out["guide_step_rms"] = squared_norm((proposal - latent).detach(), self.dim_reduction).mean().sqrt()
        if self.tsym_regularizer:
            out["tsym_to_state_ratio"] = out["loss_tsym"].detach() / out["loss_guide_state"].detach().clamp_min(1e-12)
        return TensorDict(out, batch_size=[])

    def stochastic_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        r"""Eq. (10) as losses: ``loss_guide_awr`` (the clipped advantage-weighted
        log-likelihood) and ``loss_tsym``, with detached diagnostics."""
        keys = self.tensor_keys
        latent = tensordict.get(keys.latent)
        next_latent = tensordict.get(("next", keys.latent))
        advantage, weight, clipped = self.awr_weights(tensordict)
        td = tensordict.select(*self.guide_network.in_keys, strict=False)
        with self.guide_network_params.to_module(self.guide_network, preserve_module_state=False):
            dist = self.guide_network.get_dist(td)
        # Eq. (10), as a loss to minimize
        out = {"loss_guide_awr": -(weight * dist.log_prob(next_latent)).mean()}
        if self.tsym_regularizer:
            with self.tsidm_params.to_module(self.tsidm, preserve_module_state=False):
                out["loss_tsym"] = self.tsym_loss(latent, dist.rsample())
        out["advantage"] = advantage.mean()
        out["clipped_weight_fraction"] = clipped.float().mean()
        out["effective_sample_fraction"] = effective_sample_fraction(weight)
        return TensorDict(out, batch_size=[])

    @torch.no_grad()
    def awr_weights(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r"""Eq. (10)'s weights on a batch: the advantage :math:`A = r + \gamma V(z') - V(z)` (the TD(0)
        target through the value estimator), :math:`\min(\exp(\alpha A), w_{max})` and where the clip bit."""
        keys = self.tensor_keys
        td = tensordict.select(keys.latent, "next", strict=False)
        target = self.value_estimator.value_estimate(td, target_params=self.value_network_params).squeeze(-1)
        advantage = target - self._value(tensordict.get(keys.latent))
        weight = torch.exp(self.alpha * advantage)
        clipped = weight > self.max_weight
        return advantage, weight.clamp_max(self.max_weight), clipped

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        return make_td0_value_estimator(self, value_type, hyperparams)
