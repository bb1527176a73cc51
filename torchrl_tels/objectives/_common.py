"""Input checks shared by the TELS losses: one clear error per bad batch."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


#: Raised when gamma is passed to the constructor: torchrl losses take it in make_value_estimator.
GAMMA_IN_CONSTRUCTOR = (
    "gamma is no longer a constructor argument of torchrl losses: pass it with "
    "loss.make_value_estimator(gamma=...)."
)


class MissingKeyError(KeyError):
    """A required tensordict key is absent; prints its message without KeyError's quoting."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def checked_get(
    tensordict: TensorDictBase,
    key: NestedKey,
    last_dim: int | None,
    owner: str,
    *,
    check_finite: bool = True,
) -> torch.Tensor:
    """Reads ``key`` and raises one error naming the key and its shape when it is unusable.

    A missing key, a wrong trailing dimension, or a NaN/inf entry would
    otherwise surface as a shape error deep inside an MLP or as a silently
    poisoned optimizer state.
    """
    value = tensordict.get(key, None)
    if value is None:
        raise MissingKeyError(
            f"{owner}: the input tensordict has no key {key!r} "
            f"(keys present: {sorted(map(str, tensordict.keys(True, True)))}). "
            f"Rename it with {owner}.set_keys(...) if your data uses another name."
        )
    if last_dim is not None and (value.ndim == 0 or value.shape[-1] != last_dim):
        raise ValueError(
            f"{owner}: {key!r} has shape {tuple(value.shape)}, expected a trailing "
            f"dimension of {last_dim}."
        )
    if check_finite and value.is_floating_point() and not torch.isfinite(value).all():
        bad = (~torch.isfinite(value)).sum().item()
        raise ValueError(
            f"{owner}: {key!r} (shape {tuple(value.shape)}) contains {bad} NaN/inf entries."
        )
    return value


class LazyInKeysMixin:
    """``in_keys`` built on first use from ``_set_in_keys``, as torchrl losses do, so ``set_keys`` can rebuild them."""

    _in_keys = None

    @property
    def in_keys(self):
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values


def make_td0_value_estimator(loss, value_type, hyperparams: dict):
    """The body of ``make_value_estimator`` for losses whose only target is TD(0) on ``V``.

    γ and the other estimator options arrive through ``hyperparams``, as in
    every torchrl 0.14 loss; the estimator reads the loss's own key names.
    """
    from torchrl.objectives.common import LossModule
    from torchrl.objectives.utils import dispatch_value_estimator, ValueEstimators
    from torchrl.objectives.value import ValueEstimatorBase

    if value_type is None:
        value_type = loss.default_value_estimator
    if isinstance(value_type, ValueEstimatorBase) or (
        isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)
    ):
        return LossModule.make_value_estimator(loss, value_type, **hyperparams)
    keys = loss.tensor_keys
    dispatch_value_estimator(
        loss,
        value_type,
        supported=(ValueEstimators.TD0,),
        tensor_keys={
            "value_target": keys.value_target,
            "value": keys.value,
            "reward": keys.reward,
            "done": keys.done,
            "terminated": keys.terminated,
        },
        **hyperparams,
    )
