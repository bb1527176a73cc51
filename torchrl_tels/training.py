"""Small pieces the TELS recipe shares: loss sums, NaN guards, resumable state, plots."""
from __future__ import annotations

import json
import os
import random
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_tels.checkpoint import atomic_save, load_checkpoint
from torchrl_tels.errors import NonFiniteLossError, TelsError

__all__ = [
    "FiniteWatch",
    "NonFiniteLossError",
    "TRAINING_STATE_FORMAT",
    "check_finite_state",
    "get_rng_state",
    "is_user_error",
    "load_training_state",
    "plot_curves",
    "save_training_state",
    "set_rng_state",
    "sum_losses",
    "write_json",
    "write_text",
]

TRAINING_STATE_FORMAT = "torchrl_tels.training_state/v1"


def sum_losses(losses: TensorDictBase) -> torch.Tensor:
    """The objective a TorchRL loss module reports: the sum of its ``loss_*`` entries."""
    return sum(value for key, value in losses.items() if key.startswith("loss_"))


class FiniteWatch:
    """Catches a non-finite ``loss_*`` without a host synchronization per step.

    :meth:`update` records, on the losses' device, the first step at which each term
    was not finite; :meth:`check`, called at log intervals, raises
    :class:`NonFiniteLossError` naming that term and step. On a GPU this keeps the
    training loop free of ``.item()`` calls between log intervals. With ``entries``
    (names for the entries of a loss with a leading dimension, e.g. one per seed),
    the error also names the first entry that went non-finite.
    """

    def __init__(self, stage: str, entries: Sequence[str] | None = None):
        self.stage = stage
        self.entries = list(entries) if entries else None
        self.keys: list[str] | None = None  # the watched ``loss_*`` terms, in the losses' order
        self.first_bad: torch.Tensor | None = None  # per term: the first bad step, -1 while finite
        self.values: torch.Tensor | None = None  # per term: the first bad value
        self.where: torch.Tensor | None = None  # per term: the entry it appeared in

    def update(self, losses: TensorDictBase, step: int) -> None:
        # One stacked test for every term: a handful of kernels per step whatever the number of terms,
        # which matters once the step itself is compiled.
        if self.keys is None:
            self.keys = [key for key in losses.keys() if key.startswith("loss_")]
        values = torch.stack([losses.get(key).detach().reshape(-1).float() for key in self.keys])
        bad = ~torch.isfinite(values)  # [terms, entries]
        index = bad.to(torch.uint8).argmax(-1)  # the first non-finite entry of each term (0 when none is)
        if self.first_bad is None:
            self.first_bad = torch.full((len(self.keys),), -1, dtype=torch.long, device=values.device)
            self.values = torch.zeros(len(self.keys), device=values.device)
            self.where = torch.zeros(len(self.keys), dtype=torch.long, device=values.device)
        newly = bad.any(-1) & (self.first_bad < 0)
        self.first_bad = torch.where(newly, step, self.first_bad)
        self.values = torch.where(newly, values.gather(-1, index[:, None]).squeeze(-1), self.values)
        self.where = torch.where(newly, index, self.where)

    def check(self) -> None:
        if self.first_bad is None:
            return
        first_bad = self.first_bad.tolist()
        bad = [k for k, first in enumerate(first_bad) if first >= 0]
        if bad:
            k = min(bad, key=lambda term: first_bad[term])  # the earliest; ties go to the first term
            entry = f" ({self.entries[self.where[k].item()]})" if self.entries else ""
            raise NonFiniteLossError(
                f"{self.stage}: {self.keys[k]}{entry} became {self.values[k].item()} at step {first_bad[k]}; the "
                f"run stops here and the last good checkpoint is kept unchanged."
            )


def _tensors(obj: Any, prefix: str = ""):
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, Mapping):
        for key, value in obj.items():
            yield from _tensors(value, f"{prefix}.{key}" if prefix else str(key))
    elif isinstance(obj, (list, tuple)):
        for index, value in enumerate(obj):
            yield from _tensors(value, f"{prefix}[{index}]")


def check_finite_state(state: Any, what: str) -> None:
    """Raises :class:`NonFiniteLossError` naming the first floating-point tensor of ``state`` holding NaN/inf.

    Run before a checkpoint is written, so that weights (or optimizer
    moments) ruined by a non-finite gradient never replace the last good file.
    """
    for name, tensor in _tensors(state):
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise NonFiniteLossError(
                f"{what}: {name} holds NaN or inf; it is not written and the last good checkpoint is kept."
            )


def is_user_error(err: BaseException) -> bool:
    """Whether ``err`` is a deliberate report about the user's input, to be shown as one line."""
    return isinstance(err, TelsError)


def get_rng_state() -> dict[str, Any]:
    """Every RNG the training loop draws from (replay sampling, dropout, numpy, python)."""
    py_state = random.getstate()
    cuda = {"cuda": torch.cuda.get_rng_state_all()} if torch.cuda.is_available() else {}
    return {
        **cuda,  # dropout on a GPU draws from the CUDA generators
        "torch": torch.get_rng_state(),
        "numpy": torch.from_numpy(np.random.get_state()[1].astype(np.int64)),
        "numpy_pos": int(np.random.get_state()[2]),
        "python": [int(x) for x in py_state[1]],
        "python_pos": py_state[2] if py_state[2] is None else float(py_state[2]),
    }


def set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((3, tuple(state["python"]), state["python_pos"]))


def save_training_state(path: str | os.PathLike, state: Mapping[str, Any]) -> None:
    """Writes the full training state atomically (temp file + rename), refusing NaN/inf tensors."""
    check_finite_state(state, f"checkpoint {Path(path).name}")
    atomic_save({"format": TRAINING_STATE_FORMAT, **state}, path)


def load_training_state(path: str | os.PathLike) -> dict[str, Any]:
    """Reads a state written by :func:`save_training_state` (``weights_only=True``)."""
    return load_checkpoint(path, TRAINING_STATE_FORMAT)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Text, written to a temporary file and renamed, so a reader never sees half a file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # per process: concurrent writers never share one
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | os.PathLike, payload: Mapping[str, Any]) -> None:
    """JSON, written atomically as :func:`write_text` does."""
    write_text(path, json.dumps(payload, indent=2, sort_keys=True))


def plot_curves(
    series: Mapping[str, Sequence[tuple[int, float]]],
    path: str | os.PathLike,
    *,
    title: str,
    xlabel: str = "step",
    ylabel: str = "value",
    logy: bool = False,
    spread: Mapping[str, Sequence[tuple[int, Sequence[float]]]] | None = None,
) -> None:
    """One PNG with a line per named series of ``(step, value)`` pairs, written atomically.

    ``spread`` gives, for a series, the values behind each of its points (an evaluation's episode scores): they
    are drawn as dots, with the band between their 25th and 75th percentiles, so the plot shows how much the
    episodes disagree and not only their mean.
    """
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, points in series.items():
        if points:
            steps, values = zip(*points)
            line, = ax.plot(steps, values, label=name)
            behind = [(step, list(v)) for step, v in (spread or {}).get(name, []) if len(v)]
            if behind:
                at = [step for step, _ in behind]
                ax.fill_between(at, [np.percentile(v, 25) for _, v in behind], [np.percentile(v, 75) for _, v in behind],
                                color=line.get_color(), alpha=0.2, lw=0, label=f"{name}: 25-75 % of episodes")
                ax.scatter([s for s, v in behind for _ in v], [x for _, v in behind for x in v], s=6,
                           color=line.get_color(), alpha=0.4, lw=0, label=f"{name}: episodes")
    if logy:
        ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if any(series.values()):
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
