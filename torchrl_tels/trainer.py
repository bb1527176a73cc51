"""The pieces of a run as functions of a recipe config, for scripts and tests that rebuild part of a run from a
hydra config or a finished run's ``config.yaml``.

Each function turns the config into a :class:`~torchrl_tels.config.RunSpec` (unvalidated: an entry the config
lacks reads as its default) and calls the :mod:`torchrl_tels.run` piece of the same name, for one seed run
plainly; the recipe itself builds its spec once and calls those pieces directly.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

from tensordict import TensorDictBase

from torchrl_tels import monitor as _monitor
from torchrl_tels import run as _run
from torchrl_tels.config import RunSpec
from torchrl_tels.envs import DeploymentMonitor, Task
from torchrl_tels.modules import TSIDM
from torchrl_tels.run import RunState, Stage2
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.seeds import SeedAxis, SeedRNG

__all__ = [
    "MonitorFit", "RunState", "StackedStage2", "autocast", "check_monitor_data", "check_same_stage1_length",
    "compile_options", "diagnostic_indices", "evaluate", "fit_tsidm", "make_compiled_step", "make_data",
    "make_monitor", "make_stage1", "make_stage2", "make_tsidm", "make_tsidm_loss", "monitor_in_background",
    "print_plan", "sample_seeds",
]


def spec_of(cfg) -> RunSpec:
    """The run spec of ``cfg``, unvalidated."""
    return RunSpec.from_config(cfg, validate=False)


def autocast(cfg):
    """bf16 matmuls on the run's device (CPU or CUDA) when ``precision`` is or resolves to bf16; fp32 otherwise."""
    return spec_of(cfg).precision_context()()


def compile_options(cfg) -> dict:
    """The ``compile`` group as :func:`~torchrl_tels.compile.compile_update`'s keywords."""
    return vars(spec_of(cfg).compile).copy()


def make_compiled_step(loss_module, optim, cfg):
    """:func:`~torchrl_tels.run.loop.make_train_step` with the run's precision and ``compile`` switches."""
    spec = spec_of(cfg)
    return _run.make_train_step(loss_module, optim, spec.precision_context(), spec.compile)


def make_data(cfg) -> tuple[TensorDictBase, Task]:
    return _run.make_data(spec_of(cfg))


def print_plan(cfg, n_transitions: int) -> None:
    _run.print_plan(spec_of(cfg), n_transitions)


def diagnostic_indices(cfg, n_transitions: int):
    return _run.diagnostic_indices(spec_of(cfg), n_transitions)


def check_same_stage1_length(cfg, datas: Sequence, seeds: Sequence[int]) -> int:
    return _run.check_same_stage1_length(spec_of(cfg).tsidm, datas, seeds)


def make_tsidm(cfg, data: TensorDictBase) -> TSIDM:
    return _run.make_tsidm(spec_of(cfg).tsidm, data)


def make_tsidm_loss(cfg, tsidm: TSIDM, beta: float):
    return _run.make_tsidm_loss(spec_of(cfg).tsidm, tsidm, beta)


def fit_tsidm(cfg, data: TensorDictBase, beta: float, run: RunState, run_dir: RunFolder | Path, logger=None):
    """Stage 1 for one β on torch's global stream as it stands: ``(tsidm, final losses, history)``."""
    spec = spec_of(cfg)
    return _run.fit_tsidm(spec, [data], beta, SeedAxis([spec.seed], stacked=False), run, RunFolder(run_dir),
                          logger)[0]


def make_stage1(cfg, data: TensorDictBase, run: RunState, run_dir: RunFolder | Path, logger=None,
                pretrained: TSIDM | None = None) -> TSIDM:
    """Algorithm 1, lines 1-4, for a plain run writing into ``run_dir``."""
    spec, folder = spec_of(cfg), RunFolder(run_dir)
    return _run.make_stage1(spec, [data], SeedAxis([spec.seed], stacked=False), run, folder, [run], [folder],
                            logger, pretrained)[0]


class OneSeedStage2(Stage2):
    """A plain run's :class:`~torchrl_tels.run.Stage2`, its seed's actor, data and target updater at hand."""

    def __getattr__(self, name: str):
        return getattr(self.__dict__["stages"][0], name)


def make_stage2(cfg, data: TensorDictBase, tsidm: TSIDM, action_spec) -> OneSeedStage2:
    """Stage 2 of a plain run: the frozen TS-IDM, the encoded data, V, π_g and the actor."""
    spec = spec_of(cfg)
    stage = _run.make_seed_stage2(spec, data, tsidm, action_spec)
    return OneSeedStage2([stage], SeedAxis([spec.seed], stacked=False), spec.precision_context(), spec.compile)


def StackedStage2(stages: Sequence[OneSeedStage2], rng: SeedRNG, labels: Sequence[str]) -> Stage2:
    """The one-seed stage 2s of :func:`make_stage2`, each built on its stream of ``rng``, stacked as one update;
    ``labels`` are ``"seed <k>"``."""
    axis = SeedAxis([int(label.removeprefix("seed ")) for label in labels], stacked=True, rng=rng)
    first = stages[0]
    return Stage2([stage.stages[0] for stage in stages], axis, first.amp, first.compile)


def sample_seeds(buffers: Sequence, rng: SeedRNG) -> TensorDictBase:
    """One batch per seed, each drawn from its own buffer on its stream of ``rng``, stacked ``[seeds, batch]``."""
    return SeedAxis(list(range(len(buffers))), stacked=True, rng=rng).sample(buffers)


def evaluate(cfg, actor, env, task: Task, step: int, latent_stats: dict,
             monitor: DeploymentMonitor | None = None) -> dict:
    spec = spec_of(cfg)
    return _run.evaluate(actor, env, task, step, latent_stats, eval=spec.eval, seed=spec.seed, compile=spec.compile,
                         monitor=monitor)


def make_monitor(cfg, data: TensorDictBase, run_dir: RunFolder | Path) -> DeploymentMonitor:
    return _monitor.make_monitor(spec_of(cfg), data, run_dir)


def check_monitor_data(cfg, data: TensorDictBase) -> None:
    _monitor.check_monitor_data(spec_of(cfg), data)


def monitor_in_background(cfg) -> bool:
    return _monitor.monitor_in_background(spec_of(cfg))


def MonitorFit(cfg, data: TensorDictBase, run_dir: RunFolder | Path, background: bool) -> _monitor.MonitorFit:
    return _monitor.MonitorFit(spec_of(cfg), data, run_dir, background)
