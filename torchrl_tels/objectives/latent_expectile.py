"""Latent state-value learning by expectile regression, paper Eq. (8)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import ValueEstimators

from torchrl_tels.modules.actors import LATENT_KEY
from torchrl_tels.objectives._common import (
    checked_get, GAMMA_IN_CONSTRUCTOR, LazyInKeysMixin, make_td0_value_estimator, SelectableOutKeysMixin,
)

__all__ = ["LatentExpectileLoss", "expectile_loss"]


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    r""":math:`L_2^\tau(u) = |\tau - \mathbb{1}(u < 0)|\,u^2` (paper Eq. 1), elementwise."""
    weight = torch.where(diff < 0, 1.0 - expectile, expectile)
    return weight * diff.pow(2)


class LatentExpectileLoss(SelectableOutKeysMixin, LazyInKeysMixin, LossModule):
    r"""Expectile regression of a latent state value (paper §3.2, Eq. 8).

    .. math::

        \min_V \; \mathbb{E}_{(s, r, s')\sim\mathcal{D}}
        \Big[L_2^\tau\big(r + \gamma (1 - d)\,\bar V(\phi_s(s')) - V(\phi_s(s))\big)\Big]

    with :math:`L_2^\tau(u) = |\tau - \mathbb{1}(u<0)|u^2` and :math:`\bar V` a
    target network. Eq. (8) leaves the terminal mask :math:`(1-d)` implicit;
    here :math:`d` is ``("next", "terminated")``, as for every TorchRL TD target.

    The latents :math:`z_s = \phi_s(s)` and :math:`z_{s'}` are read from the
    tensordict (``"latent"`` and ``("next", "latent")``): encode the data once
    with :class:`~torchrl_tels.envs.TSIDMEncoderTransform` (Algorithm 1, line 6).

    The target is computed by TorchRL's value estimator (TD(0) by default);
    set γ with ``loss.make_value_estimator(gamma=0.99)`` as for every 0.14
    loss. Update :math:`\bar V` with
    ``torchrl.objectives.SoftUpdate(loss, tau=0.05)`` (Table 11: target moving
    average 0.05).

    The output holds ``loss_value`` and the detached batch means
    ``state_value`` and ``value_target``; ``select_out_keys`` keeps a subset
    (``out_keys_source`` still lists all three).

    Args:
        value_network: a :class:`~tensordict.nn.TensorDictModule` reading the
            latent key and writing ``"state_value"``.
        expectile: :math:`\tau` in (0, 1) (Table 11: 0.7 MuJoCo, 0.9 AntMaze).

    Examples:
        >>> from torchrl.modules import MLP, ValueOperator
        >>> value = ValueOperator(MLP(in_features=11, out_features=1, num_cells=[64, 64]),
        ...                       in_keys=["latent"])
        >>> loss = LatentExpectileLoss(value, expectile=0.7)
        >>> loss.make_value_estimator(gamma=0.99)
        >>> _ = loss.select_out_keys("loss_value")
        >>> n = 8
        >>> loss_value = loss(latent=torch.randn(n, 11), next_latent=torch.randn(n, 11),
        ...                   next_reward=torch.randn(n, 1), next_done=torch.zeros(n, 1, dtype=torch.bool),
        ...                   next_terminated=torch.zeros(n, 1, dtype=torch.bool))
        >>> loss_value.backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`LatentExpectileLoss`.

        Attributes:
            latent (NestedKey): the latent state :math:`z_s`; :math:`z_{s'}` is
                read from ``("next", latent)``. Defaults to ``"latent"``.
            value (NestedKey): where the value network writes :math:`V(z)`.
                Defaults to ``"state_value"``.
            value_target (NestedKey): where the TD target is written.
                Defaults to ``"value_target"``.
            reward (NestedKey): the reward, read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): masks the bootstrap, read under ``"next"``.
                Defaults to ``"terminated"``.
        """

        latent: NestedKey = LATENT_KEY
        value: NestedKey = "state_value"
        value_target: NestedKey = "value_target"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0

    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        value_network: TensorDictModule,
        *,
        expectile: float = 0.7,
        gamma: float | None = None,
        check_inputs: bool = True,
    ) -> None:
        self._in_keys = None
        super().__init__()
        if gamma is not None:
            raise TypeError(GAMMA_IN_CONSTRUCTOR)
        expectile = float(expectile)
        if not (math.isfinite(expectile) and 0.0 < expectile < 1.0):
            raise ValueError(f"LatentExpectileLoss: expectile must lie in (0, 1), got {expectile}.")
        self.expectile = expectile
        self.check_inputs = check_inputs
        self.convert_to_functional(value_network, "value_network", create_target_params=True)

    def _set_in_keys(self):
        keys = self.tensor_keys
        self._in_keys = [
            keys.latent,
            ("next", keys.latent),
            ("next", keys.reward),
            ("next", keys.done),
            ("next", keys.terminated),
        ]

    def _all_out_keys(self):
        return ["loss_value", "state_value", "value_target"]

    def _check(self, tensordict: TensorDictBase) -> None:
        owner = type(self).__name__
        keys = self.tensor_keys
        latent = checked_get(tensordict, keys.latent, None, owner)
        checked_get(tensordict, ("next", keys.latent), latent.shape[-1], owner)
        checked_get(tensordict, ("next", keys.reward), None, owner)
        checked_get(tensordict, ("next", keys.terminated), None, owner)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.check_inputs:
            self._check(tensordict)
        td = tensordict.select(*self.value_network.in_keys, "next", strict=False)
        with torch.no_grad():
            target = self.value_estimator.value_estimate(
                td, target_params=self.target_value_network_params
            ).squeeze(-1)
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            self.value_network(td)
        value = td.get(self.tensor_keys.value).squeeze(-1)
        # Eq. (8)
        loss_value = expectile_loss(target - value, self.expectile).mean()
        out = TensorDict(
            {
                "loss_value": loss_value,
                "state_value": value.detach().mean(),
                "value_target": target.mean(),
            },
            batch_size=[],
        )
        return self._selected_output(out)

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        return make_td0_value_estimator(self, value_type, hyperparams)
