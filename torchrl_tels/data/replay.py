"""Replay buffers over a fixed offline dataset."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal

import torch
from tensordict import TensorDictBase
from torchrl.data import (
    LazyTensorStorage,
    RandomSampler,
    SamplerWithoutReplacement,
    TensorDictReplayBuffer,
)
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.envs import Transform

__all__ = ["make_offline_replay_buffer"]

TransformLike = Transform | Callable[[TensorDictBase], TensorDictBase]


def _as_list(transforms: TransformLike | Sequence[TransformLike] | None) -> list:
    if transforms is None:
        return []
    if isinstance(transforms, Sequence):
        return list(transforms)
    return [transforms]


def make_offline_replay_buffer(
    data: TensorDictBase,
    batch_size: int,
    *,
    transforms: TransformLike | Sequence[TransformLike] | None = None,
    write_transforms: TransformLike | Sequence[TransformLike] | None = None,
    sampler: Literal["random", "without_replacement"] | Sampler = "random",
    prefetch: int | None = None,
    seed: int | None = None,
    device: torch.device | str | None = None,
) -> TensorDictReplayBuffer:
    """Build a replay buffer holding a whole offline dataset.

    The buffer stores ``data`` in a :class:`~torchrl.data.LazyTensorStorage`
    sized to the dataset (so nothing is ever overwritten) and samples
    ``batch_size`` transitions per :meth:`~torchrl.data.ReplayBuffer.sample`
    call.

    Args:
        data: transitions with a single batch dimension, e.g. the output of
            :func:`~torchrl_tels.data.load_dataset`. It is not modified.
        batch_size: transitions per sample; ``0 < batch_size <= len(data)``.

    Keyword Args:
        transforms: transform(s) applied to every sampled batch (read time).
        write_transforms: transform(s) applied once, when the dataset is
            written (``rb.append_transform(t, invert=True)``), e.g. an
            :class:`~torchrl.envs.ObservationNorm` so the dataset is encoded a
            single time. At sample time their *inverse* runs, which is a no-op
            for transforms without ``in_keys_inv`` (the usual case).
        sampler: ``"random"`` (uniform with replacement),
            ``"without_replacement"`` (epochs over the shuffled dataset; an
            incomplete last batch of an epoch is dropped so every batch has
            ``batch_size`` rows) or a :class:`~torchrl.data.replay_buffers.Sampler`.
        prefetch: number of batches prepared ahead in background threads.
        seed: seed of a dedicated :class:`torch.Generator` for sampling, so
            the sample sequence does not depend on the global RNG.
        device: device of the storage (e.g. ``"cuda"`` to sample on the GPU).

    Returns:
        A filled :class:`~torchrl.data.TensorDictReplayBuffer`.

    Raises:
        TypeError: if ``data`` is not a TensorDict with one batch dimension.
        ValueError: if ``batch_size`` is not in ``(0, len(data)]`` or
            ``sampler`` is unknown.

    Examples:
        >>> data = load_dataset("hopper-medium-v2-10k")
        >>> rb = make_offline_replay_buffer(data, 256, seed=0)
        >>> rb.sample()["observation"].shape
        torch.Size([256, 11])
    """
    if not isinstance(data, TensorDictBase):
        raise TypeError(
            f"data must be a TensorDict of transitions, got {type(data).__name__}."
        )
    if data.batch_dims != 1:
        raise TypeError(
            "data must have one batch dimension (one row per transition), got "
            f"batch_size {tuple(data.batch_size)}."
        )
    num_transitions = data.batch_size[0]
    if not 0 < batch_size <= num_transitions:
        raise ValueError(
            f"batch_size must be in (0, {num_transitions}] for a dataset of "
            f"{num_transitions} transitions, got {batch_size}."
        )

    if isinstance(sampler, Sampler):
        sampler_instance = sampler
    elif sampler == "random":
        sampler_instance = RandomSampler()
    elif sampler == "without_replacement":
        sampler_instance = SamplerWithoutReplacement(drop_last=True)
    else:
        raise ValueError(
            f"Unknown sampler {sampler!r}; expected 'random', 'without_replacement' "
            "or a torchrl Sampler instance."
        )

    generator = None
    if seed is not None:
        generator = torch.Generator(device="cpu").manual_seed(seed)

    replay_buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(num_transitions, device=device or "cpu"),
        sampler=sampler_instance,
        batch_size=batch_size,
        prefetch=prefetch,
        generator=generator,
    )
    # Write transforms go in before the data and read transforms after it:
    # ``extend`` runs the inverse of every registered transform.
    for transform in _as_list(write_transforms):
        replay_buffer.append_transform(transform, invert=True)
    # ``extend`` writes an "index" entry into the tensordict it is given: hand
    # it a shallow copy so the caller's dataset is left untouched.
    replay_buffer.extend(data.copy())
    for transform in _as_list(transforms):
        replay_buffer.append_transform(transform)
    return replay_buffer
