"""Reduced-size datasets and region deletion, as used in the TELS experiments.

The paper's point is learning from small data: 5k-100k transitions cut from
larger D4RL datasets, either as whole trajectories or as uniformly
subsampled transitions. Its out-of-distribution test deletes the
transitions whose (x, y) position lies in given regions of a maze.

All functions take and return TensorDicts in the layout of
:func:`~torchrl_tels.data.load_dataset` and are deterministic given ``seed``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase

from torchrl_tels.data.datasets import DatasetError

__all__ = [
    "PAPER_SUBSET_SIZES",
    "SUBSET_MODES",
    "subset_dataset",
    "split_trajectories",
    "trajectory_ids",
    "subset_trajectories",
    "subsample_transitions",
    "points_in_boxes",
    "delete_regions",
]

#: Dataset sizes (transitions) studied in the paper.
PAPER_SUBSET_SIZES: tuple[int, ...] = (5_000, 10_000, 50_000, 100_000)

Box = tuple[float, float, float, float]


def _generator(seed: int) -> torch.Generator:
    return torch.Generator(device="cpu").manual_seed(seed)


def _check_size(data: TensorDictBase, size: int) -> None:
    if not 0 < size <= len(data):
        raise DatasetError(
            f"size must be in (0, {len(data)}] for a dataset of {len(data)} "
            f"transitions, got {size}."
        )


def subset_trajectories(
    data: TensorDictBase, size: int, seed: int, *, trim: bool = False
) -> TensorDictBase:
    """Draw whole trajectories at random until ``size`` transitions are reached.

    Trajectories (runs of equal ``"episode"`` ids) are visited in a random
    order fixed by ``seed`` and kept until the kept transitions reach
    ``size``. The last trajectory kept usually overshoots the target:

    * ``trim=False`` (default) keeps it whole, so the subset holds
      ``size`` transitions or a little more, and only complete trajectories;
    * ``trim=True`` cuts it so the subset holds exactly ``size`` transitions;
      the cut transition becomes a truncation (``("next", "truncated")`` and
      ``("next", "done")`` set) since the trajectory goes on past it.

    The kept trajectories appear in their original order and are renumbered
    ``0, 1, ...`` in ``"episode"``.

    Args:
        data: transitions with an ``"episode"`` entry.
        size: target number of transitions, ``0 < size <= len(data)``.
        seed: seed of the random trajectory order.

    Keyword Args:
        trim: cut the last trajectory to hit ``size`` exactly.

    Returns:
        A new TensorDict (the input is not modified).
    """
    _check_size(data, size)
    if "episode" not in data.keys():
        raise DatasetError(
            "subset_trajectories needs an 'episode' entry to find trajectories."
        )
    episode = data.get("episode")
    # Trajectories are contiguous runs of equal ids; find their start/length
    # so that repeated ids in separate runs count as separate trajectories.
    run_start = torch.ones(len(episode), dtype=torch.bool)
    run_start[1:] = episode[1:] != episode[:-1]
    starts = run_start.nonzero().squeeze(-1)
    lengths = torch.diff(starts, append=torch.tensor([len(episode)]))

    order = torch.randperm(len(starts), generator=_generator(seed))
    cumulative = lengths[order].cumsum(0)
    # Number of trajectories needed: the first prefix reaching the target.
    num_kept = int(torch.searchsorted(cumulative, size)) + 1
    kept = order[:num_kept].sort().values

    rows = torch.cat(
        [torch.arange(starts[i], starts[i] + lengths[i]) for i in kept.tolist()]
    )
    new_episode = torch.repeat_interleave(torch.arange(num_kept), lengths[kept])
    subset = data[rows]
    subset.set("episode", new_episode)
    if trim and len(subset) > size:
        # Drop the tail of the trajectory drawn last (the overshooting one).
        last_drawn = int((kept == order[num_kept - 1]).nonzero())
        overshoot = len(subset) - size
        keep_mask = torch.ones(len(subset), dtype=torch.bool)
        end_of_last = int(lengths[kept][: last_drawn + 1].sum())
        keep_mask[end_of_last - overshoot : end_of_last] = False
        subset = subset[keep_mask]
        cut_row = end_of_last - overshoot - 1
        subset.set_at_(("next", "truncated"), True, cut_row)
        subset.set_at_(("next", "done"), True, cut_row)
        subset.set_at_(("next", "terminated"), False, cut_row)
    return subset


def trajectory_ids(data: TensorDictBase) -> torch.Tensor:
    """``0, 1, ...``: the index of each row's trajectory, a trajectory being a run of equal ``"episode"`` ids."""
    if "episode" not in data.keys():
        raise DatasetError("the data has no 'episode' entry, so its trajectories cannot be told apart.")
    episode = data.get("episode").reshape(-1)
    start = torch.ones(len(episode), dtype=torch.bool, device=episode.device)
    start[1:] = episode[1:] != episode[:-1]
    return start.cumsum(0) - 1


def split_trajectories(data: TensorDictBase, fraction: float, seed: int) -> tuple[TensorDictBase, TensorDictBase]:
    """Splits ``data`` into (whole trajectories holding about ``fraction`` of the transitions, the rest).

    Trajectories are drawn in a random order fixed by ``seed`` until ``fraction`` of the transitions
    is reached; both parts keep the original row order. Transitions of one trajectory are strongly
    dependent, so a part held out for calibration or testing must not share trajectories with the
    part a model was fitted on. Both parts are refused empty.
    """
    if not 0.0 < float(fraction) < 1.0:
        raise DatasetError(f"split_trajectories: fraction must lie in (0, 1), got {fraction}.")
    run_id = trajectory_ids(data)
    count = int(run_id[-1]) + 1 if len(run_id) else 0
    if count < 2:
        raise DatasetError(f"split_trajectories needs at least two trajectories, the data holds {count}.")
    run_id = run_id.cpu()
    order = torch.randperm(count, generator=_generator(seed))
    lengths = torch.bincount(run_id, minlength=count)[order]
    taken = int(torch.searchsorted(lengths.cumsum(0), fraction * len(run_id))) + 1
    kept = order[: min(taken, count - 1)]
    mask = torch.isin(run_id, kept).to(data.device) if data.device is not None else torch.isin(run_id, kept)
    return data[mask], data[~mask]


def subsample_transitions(data: TensorDictBase, size: int, seed: int) -> TensorDictBase:
    """Keep ``size`` transitions drawn uniformly without replacement.

    The kept rows stay in their original order with their original
    ``"episode"`` ids (which then name the source trajectory: consecutive rows
    are generally not consecutive steps any more).

    Args:
        data: transitions.
        size: number of transitions to keep, ``0 < size <= len(data)``.
        seed: seed of the draw.

    Returns:
        A new TensorDict (the input is not modified).
    """
    _check_size(data, size)
    rows = torch.randperm(len(data), generator=_generator(seed))[:size].sort().values
    return data[rows]


#: How :func:`subset_dataset` cuts a dataset down (Appendix D.1 uses both).
SUBSET_MODES: tuple[str, ...] = ("trajectories", "transitions")


def subset_dataset(data: TensorDictBase, size: int, seed: int, mode: str = "trajectories") -> TensorDictBase:
    """The ``size``-transition subset of ``data`` that a run with this ``seed`` trains on.

    ``mode="trajectories"`` calls :func:`subset_trajectories` (whole trajectories),
    ``mode="transitions"`` calls :func:`subsample_transitions` (uniform rows). The recipe
    and the diagnostics that need to know a run's training rows both call this, so they
    draw the same subset.
    """
    if mode == "trajectories":
        return subset_trajectories(data, size, seed=seed)
    if mode == "transitions":
        return subsample_transitions(data, size, seed=seed)
    raise ValueError(f"subset mode must be one of {SUBSET_MODES}, got {mode!r}.")


def _xy(
    data: TensorDictBase, xy_slice: slice | Sequence[int], key: str
) -> torch.Tensor:
    observation = data.get(key)
    index = xy_slice if isinstance(xy_slice, slice) else list(xy_slice)
    xy = observation[:, index]
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(
            f"xy_slice={xy_slice!r} must select exactly 2 columns of {key!r} "
            f"(shape {tuple(observation.shape)}), got {tuple(xy.shape[1:])}."
        )
    return xy


def points_in_boxes(
    data: TensorDictBase,
    boxes: Sequence[Box],
    *,
    xy_slice: slice | Sequence[int] = slice(0, 2),
    key: str = "observation",
) -> torch.Tensor:
    """Boolean mask of the transitions whose (x, y) lies in any box.

    Args:
        data: transitions.
        boxes: axis-aligned boxes ``(xmin, xmax, ymin, ymax)``; bounds are
            inclusive.

    Keyword Args:
        xy_slice: columns of ``data[key]`` holding (x, y): a slice or two
            indices.
        key: entry holding the positions (the state a transition starts from).

    Returns:
        A ``(N,)`` bool tensor.
    """
    xy = _xy(data, xy_slice, key)
    inside = torch.zeros(len(xy), dtype=torch.bool)
    for box in boxes:
        if len(box) != 4:
            raise ValueError(f"A box is (xmin, xmax, ymin, ymax), got {box!r}.")
        xmin, xmax, ymin, ymax = (float(v) for v in box)
        if xmin > xmax or ymin > ymax:
            raise ValueError(
                f"Box {box!r} is empty: expected xmin <= xmax and ymin <= ymax."
            )
        inside |= (
            (xy[:, 0] >= xmin)
            & (xy[:, 0] <= xmax)
            & (xy[:, 1] >= ymin)
            & (xy[:, 1] <= ymax)
        )
    return inside


def delete_regions(
    data: TensorDictBase,
    boxes: Sequence[Box],
    ratio: float = 1.0,
    seed: int = 0,
    xy_slice: slice | Sequence[int] = slice(0, 2),
    *,
    key: str = "observation",
) -> TensorDictBase:
    """Delete transitions whose (x, y) falls in given regions (OOD test).

    Among the transitions whose ``data[key][:, xy_slice]`` lies inside any of
    ``boxes`` (see :func:`points_in_boxes`), ``round(ratio * n_inside)``
    chosen at random with ``seed`` are removed; everything else is kept in its
    original order. Episode flags and ids are left as they are, so a deletion
    in the middle of a trajectory leaves a gap in its observation chain, as in
    the POR/TELS experiments.

    Args:
        data: transitions.
        boxes: axis-aligned boxes ``(xmin, xmax, ymin, ymax)``, inclusive.
        ratio: fraction of the inside points to delete, in ``[0, 1]``.
        seed: seed choosing which inside points go when ``ratio < 1``.
        xy_slice: columns of ``data[key]`` holding (x, y).

    Keyword Args:
        key: entry holding the positions.

    Returns:
        A new TensorDict (the input is not modified).
    """
    if not 0.0 <= ratio <= 1.0:
        raise ValueError(f"ratio must be in [0, 1], got {ratio}.")
    inside_rows = points_in_boxes(data, boxes, xy_slice=xy_slice, key=key).nonzero()
    inside_rows = inside_rows.squeeze(-1)
    num_deleted = int(round(ratio * len(inside_rows)))
    chosen = torch.randperm(len(inside_rows), generator=_generator(seed))[:num_deleted]
    keep = torch.ones(len(data), dtype=torch.bool)
    keep[inside_rows[chosen]] = False
    return data[keep]
