"""What the TELS losses share: one clear error per bad batch, lazy in_keys, selectable out_keys, TD(0)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key_list

from torchrl_tels.errors import OutKeysError


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


class SelectableOutKeysMixin:
    """``out_keys`` that follow the loss's options until :meth:`select_out_keys` narrows them.

    A subclass lists in ``_all_out_keys`` every entry its ``forward`` writes under
    its current options and passes its output through ``_selected_output``.
    ``out_keys_source`` is always that full list; ``out_keys`` is the selection,
    or the full list when nothing was selected, so it tracks the options instead
    of freezing them at the first read.

    tensordict's ``select_out_keys`` filters through a forward hook that decides
    from the input whether a call was dispatched, and a batch lacking a key the
    loss lists but can do without (``("next", "done")`` for TD(0)) makes that hook
    return the unfiltered output, or fail. Filtering in ``forward`` serves a tensordict
    call and a ``@dispatch`` keyword call (which returns ``out_keys`` in order)
    alike.
    """

    _selected_out_keys: list[NestedKey] | None = None

    def _all_out_keys(self) -> list[NestedKey]:
        raise NotImplementedError

    @property
    def out_keys_source(self) -> list[NestedKey]:
        return unravel_key_list(self._all_out_keys())

    @property
    def out_keys(self) -> list[NestedKey]:
        if self._selected_out_keys is None:
            return self.out_keys_source
        return list(self._selected_out_keys)

    @out_keys.setter
    def out_keys(self, values) -> None:
        # Settable as on torchrl's losses: a subset of out_keys_source, or None for all of it.
        if values is None:
            self._selected_out_keys = None
            return
        keys = self._as_out_keys(values)
        self._check_out_keys(keys, self.out_keys_source)
        self._selected_out_keys = keys

    def select_out_keys(self, *out_keys: NestedKey):
        """Keeps only ``out_keys`` in the output; ``reset_out_keys()`` undoes it.

        Selects among the current ``out_keys``, so a second call narrows the
        first, as for every TensorDictModule. Keyword calls
        (``loss(observation=..., ...)``) then return the selected entries in the
        order given here. The objective is the sum of the ``loss_*`` entries
        that remain.
        """
        keys = self._as_out_keys(out_keys)
        self._check_out_keys(keys, self.out_keys)
        self._selected_out_keys = keys
        return self

    def reset_out_keys(self):
        """Restores the full output, ``out_keys_source``."""
        self._selected_out_keys = None
        # also drops any hook that tensordict's own select_out_keys registered
        return super().reset_out_keys()

    @staticmethod
    def _as_out_keys(keys) -> list[NestedKey]:
        # A list is never a nested key; as a tuple it reaches the hint below
        # instead of failing inside unravel_key_list.
        return unravel_key_list([tuple(key) if isinstance(key, list) else key for key in keys])

    def _check_out_keys(self, keys: list[NestedKey], available: list[NestedKey]) -> None:
        unknown = [key for key in keys if key not in available]
        if not unknown:
            return
        message = f"{type(self).__name__}: cannot select {', '.join(map(repr, unknown))}: not among {available}."
        if available != self.out_keys_source:
            message += f" An earlier select_out_keys narrowed them; reset_out_keys() restores {self.out_keys_source}."
        if len(keys) == 1 and isinstance(keys[0], tuple) and all(part in available for part in keys[0]):
            message += f" Pass the keys as separate arguments: select_out_keys({', '.join(map(repr, keys[0]))})."
        raise OutKeysError(message)

    def _selected_output(self, out: TensorDictBase) -> TensorDictBase:
        if self._selected_out_keys is None:
            return out
        missing = [key for key in self._selected_out_keys if key not in out.keys(True)]
        if missing:
            # The options changed after the selection (e.g. ``tsym_regularizer`` switched off).
            raise OutKeysError(
                f"{type(self).__name__}: the selected {', '.join(map(repr, missing))} is no longer written "
                f"under the loss's current options (out_keys_source: {self.out_keys_source}); "
                f"call reset_out_keys() or select again."
            )
        return out.select(*self._selected_out_keys)


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
