"""``torch.compile`` and CUDA graphs for a train step, switched as torchrl's ``sota-implementations`` do.

A train step of either stage is one Python function of the batch: the loss forward pass, the backward
pass, the optimizer step and the target update (``torchrl_tels.run.loop.make_train_step``). At the batch
sizes and widths of TELS a GPU is idle most of such a step: its cost is Python, tensordict and
kernel-launch overhead, not arithmetic. Two tools remove that overhead:

* ``torch.compile`` fuses a loss's many small kernels and traces its functional-parameter swaps
  (``to_module``) and key handling away. The recipe compiles each loss's forward pass (the backward
  follows through AOTAutograd) and leaves Adam to its fused kernel (see ``make_train_step``);
  :func:`compile_update` compiles a whole function, such as the evaluation policy's call;
* :class:`tensordict.nn.CudaGraphModule` records the whole step once as a CUDA graph, after ``warmup``
  eager calls, and replays it: one launch per step. Its optimizers must be *capturable*
  (:func:`capturable_adam`), so that Adam's step counter lives on the device.

Neither changes the arithmetic beyond float rounding (``tests/test_compile.py``). On a CPU the
recipe's widths are compute-bound and eager is the faster mode (BENCHMARKS.md, "Compiled train
steps"), so both switches are off by default.
"""
from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from typing import Any

import torch

__all__ = ["COMPILE_MODES", "CUDAGRAPH_WARMUP", "capturable_adam", "compile_update", "precision_context"]

#: ``compile.mode`` values: ``None`` is torch.compile's default mode.
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
#: Eager calls before a CUDA graph is recorded: the optimizer state and compiled kernels settle first.
CUDAGRAPH_WARMUP = 10


def compile_update(
    update: Callable[..., Any],
    *,
    compile: bool = False,
    cudagraphs: bool = False,
    mode: str | None = None,
    warmup: int = CUDAGRAPH_WARMUP,
) -> Callable[..., Any]:
    """``update`` wrapped by ``torch.compile`` (``compile``) and then :class:`~tensordict.nn.CudaGraphModule`
    (``cudagraphs``); ``update`` itself when both are off.

    The wrapped step returns what ``update`` returns; with ``cudagraphs``, clones of the graph's outputs
    (``CudaGraphModule`` copies them out of its static buffers at each replay).
    """
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode must be one of {COMPILE_MODES}, got {mode!r}.")
    if compile:
        update = torch.compile(update, mode=mode)
    if cudagraphs:
        from tensordict.nn import CudaGraphModule

        update = CudaGraphModule(update, warmup=warmup)
    return update


def capturable_adam(params: Iterable, *, capturable: bool = False, **options) -> torch.optim.Adam:
    """Adam with the fused kernel; ``capturable`` keeps its step counter on the parameters' device, as a
    CUDA graph needs (a CPU has no capturable fused Adam, and nothing to capture)."""
    params = list(params)
    on_cuda = bool(params) and params[0].is_cuda
    return torch.optim.Adam(params, fused=True, capturable=capturable and on_cuda, **options)


def precision_context(device: torch.device, precision: str) -> Callable[[], torch.autocast]:
    """A factory of the loss forward pass's autocast context: bf16 matmuls on ``device`` for
    ``precision="bf16"``, disabled for ``"fp32"``. Built once, outside the step, so that a compiled
    step reads no config."""
    return functools.partial(torch.autocast, torch.device(device).type, dtype=torch.bfloat16,
                             enabled=precision == "bf16")
