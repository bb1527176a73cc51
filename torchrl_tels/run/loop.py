"""The train step of a loss module and the one loop both stages run it in, with the run's cadence: log,
evaluate, checkpoint, and stop at the first non-finite loss."""
from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass
from typing import Callable

import torch
import tqdm
from tensordict import TensorDictBase

from torchrl_tels.compile import compile_update
from torchrl_tels.config import CompileSpec
from torchrl_tels.training import sum_losses

__all__ = ["Cadence", "make_train_step", "train_loop"]


def make_train_step(loss_module, optim: torch.optim.Optimizer, amp=contextlib.nullcontext,
                    options: CompileSpec = CompileSpec(), *, record_graph: bool = True) -> Callable:
    """One train step of ``loss_module`` as a function of the batch: forward (under ``amp``), backward
    of the sum of its ``loss_*`` entries (summed over seeds for a stacked loss), optimizer step.

    Returns the detached losses. ``options.compile`` compiles the loss's forward pass (its backward
    follows, through AOTAutograd) and leaves the optimizer its fused kernel: compiling the whole step
    instead breaks its graph at the backward and at the optimizer, and stage 2's two steps would then
    share compiled frames whose guard checks cost more than compiling saves (BENCHMARKS.md, "Compiled
    train steps"). With ``record_graph``, ``options.cudagraphs`` records the step as a CUDA graph
    (:func:`~torchrl_tels.compile.compile_update`); a caller that records a larger step passes ``False``."""
    if options.compile:
        # torchrl losses build their in_keys on first read; built inside the first traced call, they would
        # fail that graph's guard at the second call and compile the loss a second time.
        getattr(loss_module, "in_keys", None)
    forward = torch.compile(loss_module, mode=options.mode) if options.compile else loss_module

    def train_step(batch: TensorDictBase) -> TensorDictBase:
        with amp():
            losses = forward(batch)
        sum_losses(losses).sum().backward()  # a stacked loss: the seeds share no parameter
        optim.step()
        optim.zero_grad(set_to_none=True)
        return losses.detach()

    return compile_update(train_step, cudagraphs=options.cudagraphs and record_graph)


@dataclass(frozen=True)
class Cadence:
    """How often the loop logs, evaluates (``None``: never) and checkpoints, in steps."""

    log: int
    checkpoint: int
    evaluate: int | None = None


def train_loop(update: Callable[[int], TensorDictBase], *, start: int, total: int, cadence: Cadence, desc: str,
               check_finite: Callable[[], None], log: Callable[[int, TensorDictBase], dict],
               checkpoint: Callable[[int], None], evaluate: Callable[[int], dict] | None = None) -> None:
    """Runs ``update(step)`` for ``step`` in ``[start, total)`` with the run's cadence.

    After every ``cadence.log`` steps, ``check_finite`` (which raises at a non-finite loss, naming it) and
    ``log(steps_done, losses)``; after every ``cadence.evaluate`` steps and at the last one,
    ``evaluate(steps_done)``; after every ``cadence.checkpoint`` steps but the last, ``check_finite`` again and
    ``checkpoint(steps_done)``, so that a checkpoint never holds the weights of a diverged step; at the end,
    ``check_finite``. What ``log`` and ``evaluate`` return shows beside the progress bar.
    """
    progress = tqdm.tqdm(range(start, total), desc=desc, file=sys.stdout, initial=start, total=total,
                         mininterval=2.0)
    for step in progress:
        losses = update(step)
        done = step + 1
        if done % cadence.log == 0:
            check_finite()
            if postfix := log(done, losses):
                progress.set_postfix(**postfix)
        if evaluate is not None and (done % cadence.evaluate == 0 or done == total):
            progress.set_postfix(**evaluate(done))
        if done % cadence.checkpoint == 0 and done < total:
            check_finite()
            checkpoint(done)
    check_finite()
