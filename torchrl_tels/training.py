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
        self.first_bad: dict[str, torch.Tensor] = {}
        self.values: dict[str, torch.Tensor] = {}
        self.where: dict[str, torch.Tensor] = {}

    def update(self, losses: TensorDictBase, step: int) -> None:
        for key, value in losses.items():
            if not key.startswith("loss_"):
                continue
            flat = value.detach().reshape(-1)
            bad_entries = ~torch.isfinite(flat)
            bad = bad_entries.any()
            index = bad_entries.float().argmax()  # the first non-finite entry (0 when none is)
            first = self.first_bad.get(key)
            if first is None:
                first = self.first_bad[key] = torch.full((), -1, dtype=torch.long, device=value.device)
                self.values[key] = torch.zeros((), dtype=value.dtype, device=value.device)
                self.where[key] = torch.zeros((), dtype=torch.long, device=value.device)
            newly = bad & (first < 0)
            self.first_bad[key] = torch.where(newly, torch.full_like(first, step), first)
            self.values[key] = torch.where(newly, flat[index], self.values[key])
            self.where[key] = torch.where(newly, index, self.where[key])

    def check(self) -> None:
        for key, first in self.first_bad.items():
            if first.item() >= 0:
                entry = f" ({self.entries[self.where[key].item()]})" if self.entries else ""
                raise NonFiniteLossError(
                    f"{self.stage}: {key}{entry} became {self.values[key].item()} at step {first.item()}; the run "
                    f"stops here and the last good checkpoint is kept unchanged."
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
) -> None:
    """One PNG with a line per named series of ``(step, value)`` pairs, written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, points in series.items():
        if points:
            steps, values = zip(*points)
            ax.plot(steps, values, label=name)
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
