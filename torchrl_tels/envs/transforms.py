"""TorchRL transforms built on a trained TS-IDM."""
from __future__ import annotations

import copy
import os
from typing import Sequence

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import dispatch

from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

from torchrl_tels.modules.actors import LATENT_KEY
from torchrl_tels.modules.tsidm import TSIDM

__all__ = ["TSIDMEncoderTransform"]


class TSIDMEncoderTransform(Transform):
    r"""Encodes observations into the latent state space of a frozen TS-IDM.

    Writes :math:`z_s = \phi_s(\mathrm{normalize}(s))` (see
    :meth:`~torchrl_tels.modules.TSIDM.encode_state`) under ``out_keys`` for
    each observation entry in ``in_keys``. The TS-IDM is frozen: its
    parameters do not require gradients, encoding runs under
    :func:`torch.no_grad`, and the encoder stays in eval mode even when the
    transform or its parent is put in train mode.

    The transform works in three places:

    * **In an environment** (:class:`~torchrl.envs.TransformedEnv`): step and
      reset outputs are encoded, and the observation spec gains an
      :class:`~torchrl.data.Unbounded` entry of shape
      ``(*batch, latent_state_dim)`` and the encoder's dtype. The parent's
      observation size is checked against the TS-IDM's when the spec is built.
    * **At sample time in a replay buffer** (``rb.append_transform(t)``): each
      sampled batch is encoded, both the root entries and their ``("next", ...)``
      counterparts.
    * **At write time in a replay buffer** (``rb.append_transform(t, invert=True)``):
      the data is encoded once, when it is extended, and the stored data holds
      the latents; sampling does not run the encoder again.

    An encoder has no inverse, so :meth:`inv` leaves the data unchanged, like
    any TorchRL transform without ``in_keys_inv``. That is what makes the
    write-time use work: an inverted buffer transform runs :meth:`_call` when
    data is written and :meth:`inv` on every sample, and the pass that
    :class:`~torchrl.envs.TransformedEnv` makes through :meth:`inv` before each
    step costs nothing.

    A transform can only have one parent: use :meth:`clone` to attach the same
    encoder to a second environment or buffer. Clones share the frozen TS-IDM
    (the same module and tensors), so they cost no memory.

    Args:
        tsidm (TSIDM, str or path-like): a trained TS-IDM, or the path of a file
            written by :meth:`TSIDM.save <torchrl_tels.modules.TSIDM.save>`. A
            module is copied before being frozen, so the caller's TS-IDM can
            keep training without changing this transform's latents.
        in_keys (sequence of NestedKey, optional): raw observation entries.
            Defaults to ``["observation"]``.
        out_keys (sequence of NestedKey, optional): latent entries, one per
            ``in_keys`` entry. Defaults to ``["latent"]`` (or
            ``["<key>_latent", ...]`` when several ``in_keys`` are given).

    Keyword Args:
        keep_observation (bool, optional): if ``False``, the raw observation
            entries are removed once encoded (and dropped from the observation
            spec). Defaults to ``True``.
        observation_dim (int, optional): if given, the TS-IDM must have been
            trained on observations of that size; a checkpoint made for another
            environment is refused with a
            :class:`~torchrl_tels.checkpoint.CheckpointError` (a module with a
            :class:`ValueError`).

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_tels.envs import TSIDMEncoderTransform
        >>> from torchrl_tels.modules import TSIDM
        >>> tsidm = TSIDM(11, 3, latent_state_dim=8)
        >>> env = TransformedEnv(GymEnv("Hopper-v4"), TSIDMEncoderTransform(tsidm))
        >>> env.reset()["latent"].shape
        torch.Size([8])
        >>> # The same encoder, applied once to a dataset at write time
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
        >>> _ = rb.append_transform(env.transform.clone(), invert=True)
        >>> _ = rb.extend(env.rollout(100))
        >>> rb.sample()["next", "latent"].shape
        torch.Size([32, 8])
        >>> # From a checkpoint, refusing one trained for another task
        >>> tsidm.save("tsidm.pt")
        >>> t = TSIDMEncoderTransform.from_checkpoint("tsidm.pt", observation_dim=11)
    """

    invertible = False

    def __init__(
        self,
        tsidm: TSIDM | str | os.PathLike,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
        *,
        keep_observation: bool = True,
        observation_dim: int | None = None,
    ) -> None:
        if isinstance(tsidm, (str, os.PathLike)):
            # TSIDM.load checks observation_dim and returns a fresh module in eval mode.
            tsidm = TSIDM.load(tsidm, observation_dim=observation_dim)
        elif isinstance(tsidm, TSIDM):
            if observation_dim is not None and tsidm.observation_dim != int(observation_dim):
                raise ValueError(
                    f"{type(self).__name__}: the TS-IDM encodes observations of size "
                    f"{tsidm.observation_dim}, but observation_dim={observation_dim} was requested."
                )
            # Freezing works in place: copy so the caller's module is left trainable.
            tsidm = copy.deepcopy(tsidm)
        else:
            raise TypeError(
                f"{type(self).__name__} expects a TSIDM or the path of a saved TS-IDM, "
                f"got {type(tsidm).__name__}."
            )

        if in_keys is None:
            in_keys = ["observation"]
        in_keys = _as_key_list(in_keys)
        if out_keys is None:
            out_keys = [LATENT_KEY] if len(in_keys) == 1 else [_latent_key(key) for key in in_keys]
        out_keys = _as_key_list(out_keys)
        if len(in_keys) != len(out_keys):
            raise ValueError(
                f"{type(self).__name__}: got {len(in_keys)} in_keys and {len(out_keys)} out_keys; "
                "they are matched one to one."
            )
        if len(set(out_keys)) != len(out_keys):
            raise ValueError(f"{type(self).__name__}: out_keys must be distinct, got {out_keys}.")
        if overlap := set(in_keys) & set(out_keys):
            # Encoding in place would leave no way to tell a raw entry from an
            # encoded one, so data passed through twice would be encoded twice.
            raise ValueError(
                f"{type(self).__name__}: in_keys and out_keys must differ, but "
                f"{sorted(overlap, key=str)} are both; use keep_observation=False to drop "
                "the raw entries instead."
            )
        super().__init__(in_keys=in_keys, out_keys=out_keys)

        tsidm.requires_grad_(False)
        self.tsidm = tsidm.eval()
        self.keep_observation = bool(keep_observation)

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
        *,
        keep_observation: bool = True,
        observation_dim: int | None = None,
    ) -> "TSIDMEncoderTransform":
        """Builds the transform from a file written by :meth:`TSIDM.save`.

        Pass the environment's ``observation_dim`` to refuse, with a
        :class:`~torchrl_tels.checkpoint.CheckpointError`, a TS-IDM that was
        trained for another task.
        """
        return cls(
            os.fspath(path),
            in_keys,
            out_keys,
            keep_observation=keep_observation,
            observation_dim=observation_dim,
        )

    # ----------------------------------------------------------------- props
    @property
    def latent_state_dim(self) -> int:
        return self.tsidm.latent_state_dim

    @property
    def observation_dim(self) -> int:
        return self.tsidm.observation_dim

    @property
    def _encoder_param(self) -> torch.Tensor:
        return next(self.tsidm.state_encoder.parameters())

    def train(self, mode: bool = True) -> "TSIDMEncoderTransform":
        # The encoder is frozen: a parent (env, buffer, loss) switching to
        # train mode must not switch it out of eval mode.
        super().train(mode)
        self.tsidm.eval()
        return self

    # -------------------------------------------------------------- encoding
    def _encode(self, observation: torch.Tensor, key: NestedKey | None = None) -> torch.Tensor:
        if observation.shape[-1:] != (self.observation_dim,):
            where = f"entry {key!r}" if key is not None else "the input"
            raise ValueError(
                f"{type(self).__name__}: {where} has shape {tuple(observation.shape)}, but the "
                f"TS-IDM encodes observations of size {self.observation_dim} (last dimension)."
            )
        param = self._encoder_param
        # Gym observations are often float64 while the encoder is float32; a dataset is encoded in chunks.
        latent = self.tsidm.encode_states(observation.to(device=param.device, dtype=param.dtype))
        return latent.to(observation.device)

    def _apply_transform(self, observation: torch.Tensor) -> torch.Tensor:
        return self._encode(observation)

    def _encode_tensordict(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Encodes every ``in_key`` at the root and under ``"next"``.

        A root entry is required unless its latent is already there (data
        stored with ``keep_observation=False``); ``"next"`` entries are
        optional because environment outputs do not have them.
        """
        to_exclude = []
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            for prefix in ((), ("next",)):
                src, dst = unravel_key(prefix + (in_key,)), unravel_key(prefix + (out_key,))
                value = tensordict.get(src, None)
                if value is None:
                    if prefix or self.missing_tolerance or dst in tensordict.keys(True):
                        continue
                    raise KeyError(
                        f"{type(self).__name__}: observation entry {src!r} not found in the "
                        f"tensordict (keys: {sorted(map(str, tensordict.keys(True, True)))})."
                    )
                tensordict.set(dst, self._encode(value, src))
                if not self.keep_observation:
                    to_exclude.append(src)
        if to_exclude:
            tensordict = tensordict.exclude(*to_exclude)
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Env step output; also the write path of rb.append_transform(t, invert=True).
        return self._encode_tensordict(next_tensordict)

    @dispatch(source="in_keys", dest="out_keys")
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Replay-buffer samples (and direct calls), root and "next".
        return self._encode_tensordict(tensordict)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # The inverse path runs on every sample of an inverted (write-time)
        # buffer transform and before every env step: encoding here would
        # redo, at each sample, the work done once at write time.
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # Transform._reset is a no-op, so without this the first observation
        # of each episode would have no latent.
        return self._call(tensordict_reset)

    # ----------------------------------------------------------------- specs
    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise TypeError(
                f"{type(self).__name__} expects a Composite observation spec, "
                f"got {type(observation_spec).__name__}."
            )
        param = self._encoder_param
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            if in_key not in observation_spec.keys(True, True):
                raise KeyError(
                    f"{type(self).__name__}: the parent environment has no observation {in_key!r} "
                    f"(observation keys: {sorted(map(str, observation_spec.keys(True, True)))})."
                )
            in_spec = observation_spec[in_key]
            if in_spec.shape[-1:] != (self.observation_dim,):
                size = in_spec.shape[-1] if in_spec.shape else "scalar"
                raise ValueError(
                    f"{type(self).__name__}: the environment's observation {in_key!r} has size "
                    f"{size} (spec shape {tuple(in_spec.shape)}), "
                    f"but the TS-IDM was trained on observations of size {self.observation_dim}: "
                    "it was trained for another environment."
                )
            observation_spec[out_key] = Unbounded(
                shape=in_spec.shape[:-1] + (self.latent_state_dim,),
                dtype=param.dtype,
                device=in_spec.device,
            )
            if not self.keep_observation:
                del observation_spec[in_key]
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(in_keys={self.in_keys}, out_keys={self.out_keys}, "
            f"observation_dim={self.observation_dim}, latent_state_dim={self.latent_state_dim}, "
            f"keep_observation={self.keep_observation})"
        )


def _as_key_list(keys: NestedKey | Sequence[NestedKey]) -> list[NestedKey]:
    if isinstance(keys, (str, tuple)):
        keys = [keys]
    return [unravel_key(key) for key in keys]


def _latent_key(key: NestedKey) -> NestedKey:
    """``"pixels"`` -> ``"pixels_latent"``; ``("agent", "obs")`` -> ``("agent", "obs_latent")``."""
    if isinstance(key, str):
        return f"{key}_latent"
    return key[:-1] + (f"{key[-1]}_latent",)
