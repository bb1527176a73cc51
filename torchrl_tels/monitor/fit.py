"""The run's deployment monitor: fitted once to the training data, saved as ``monitor.pt``, and fitted beside
training in a process of its own when the machine has a core the run leaves free."""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase

from torchrl_tels.config import available_cpus, monitor_fit_options, resolve_precision, RunSpec
from torchrl_tels.data import split_trajectories, subset_trajectories, trajectory_ids
from torchrl_tels.envs import DeploymentMonitor
from torchrl_tels.errors import MonitorError
from torchrl_tels.run_folder import RunFolder

__all__ = ["MonitorFit", "check_monitor_data", "make_monitor", "monitor_data", "monitor_in_background"]


def monitor_data(spec: RunSpec, data: TensorDictBase) -> TensorDictBase:
    """The transitions the monitor fits on: all of them, or whole trajectories drawn at random (seeded by the
    run's seed) up to ``monitor.max_transitions``."""
    cap = spec.monitor.max_transitions
    return subset_trajectories(data, cap, spec.seed) if cap and len(data) > cap else data


def check_monitor_data(spec: RunSpec, data: TensorDictBase) -> None:
    """Refuses, before anything is written, data with too few trajectories for ``spec.monitor``'s calibration."""
    count = int(trajectory_ids(monitor_data(spec, data))[-1]) + 1
    need = spec.monitor.folds if spec.monitor.calibration == "cross_fit" else 2
    if count < need:
        raise MonitorError(f"the deployment monitor's {spec.monitor.calibration} calibration needs at least {need} "
                           f"trajectories, and the training data holds {count}; lower monitor.folds or use "
                           "monitor.calibration=split.")


def make_monitor(spec: RunSpec, data: TensorDictBase, run_dir: RunFolder | Path) -> DeploymentMonitor:
    """The run's deployment monitor, fitted to ``data`` as ``spec.monitor`` says (cross-fitted or split
    calibration) and saved as ``run_dir/monitor.pt``; a continuation (``resume=true``) reads that file back
    when it was fitted to the same dataset, seed and ``monitor`` settings, and refits it otherwise.

    Its detectors are a one-step dynamics ensemble and the nearest data state, combined into the
    default ``ood_score``. The TS-IDM's terms are not included: the run's TS-IDM is trained on every
    trajectory and so leaves none to calibrate them on (``DeploymentMonitor.fit`` adds them for a
    TS-IDM trained on a split).
    """
    path = RunFolder(run_dir).monitor_path
    # The ensemble trains on the CPU: in bf16 where that CPU multiplies it natively, unless the run asks for
    # fp32. Paired runs detected and alarmed as fp32 at about half the fit time (benchmarks/results/monitor/MONITOR.md).
    precision = "fp32" if spec.precision == "fp32" else resolve_precision("auto", "cpu")
    settings = spec.monitor.settings()
    fitted_for = {"dataset": str(spec.dataset.name), "seed": int(spec.seed), "precision": precision,
                  "monitor": settings}
    if spec.resume and path.is_file():
        monitor = DeploymentMonitor.load(path, observation_dim=data["observation"].shape[-1],
                                         action_dim=data["action"].shape[-1])
        if all(monitor.metadata.get(key) == value for key, value in fitted_for.items()):
            return monitor
    m = spec.monitor
    options = {**monitor_fit_options(settings), "quantile": m.quantile, "seed": spec.seed, "precision": precision}
    full = len(data)
    data = monitor_data(spec, data.cpu())  # whole trajectories: the held-out calibration splits by trajectory
    if len(data) < full:
        print(f"deployment monitor: fitted on {len(data)} of {full} transitions, whole trajectories drawn at random "
              f"(monitor.max_transitions={m.max_transitions})", flush=True)
    clock = time.perf_counter()
    with torch.random.fork_rng():  # the run's RNG streams do not depend on the monitor's settings
        if m.calibration == "cross_fit":
            monitor = DeploymentMonitor.cross_fit(data, folds=m.folds, **options)
        else:
            train, calibration = split_trajectories(data, 1.0 - float(m.holdout), spec.seed)
            monitor = DeploymentMonitor.fit(train, calibration, **options)
    print(f"deployment monitor: {m.calibration} calibration, threshold {float(monitor.threshold):.3g}, "
          f"window threshold {float(monitor.window_threshold):.3g} ({time.perf_counter() - clock:.0f} s)", flush=True)
    monitor.save(path, metadata=fitted_for)
    return monitor


def _exit_with_parent(parent: int) -> None:
    """Ends this process when the run that started it ends, however it ends. A daemon child is stopped only by
    its parent's own exit handlers, so a run killed by a signal (a scheduler's SIGTERM, SIGKILL, OOM) would leave
    the fit running on its core and writing into a run folder that may be resumed meanwhile. Linux stops the
    child itself when asked (``PR_SET_PDEATHSIG``); a parent already gone by then is checked after asking."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def _fit_monitor_in_child(spec: RunSpec, data: TensorDictBase, run_dir: str, errors, parent: int) -> None:
    """:func:`make_monitor` in a process of its own, on one thread, that ends with the run; the monitor lands in
    ``run_dir/monitor.pt``, a failure's message in ``errors``."""
    _exit_with_parent(parent)
    torch.set_num_threads(1)
    try:
        make_monitor(spec, data, Path(run_dir))
    except BaseException as err:  # reported to the parent, which raises it as one MonitorError
        errors.put(f"{type(err).__name__}: {err}")
        raise


def monitor_in_background(spec: RunSpec) -> bool:
    """``monitor.background``: ``auto`` fits the monitor beside training when the machine has a core the run's
    torch threads leave free."""
    setting = spec.monitor.background
    if setting == "auto":
        return available_cpus() > spec.threads
    return bool(setting)


class MonitorFit:
    """The run's deployment monitor (:func:`make_monitor`), fitted inline or, with ``background``, in a process
    of its own while the stages train; :meth:`get` waits for it. The two give the same monitor: its fits are
    seeded and its calibration draws on its own generators."""

    def __init__(self, spec: RunSpec, data: TensorDictBase, run_dir: RunFolder | Path, background: bool) -> None:
        self.path, self._monitor, self._process = RunFolder(run_dir).monitor_path, None, None
        self._sizes = {"observation_dim": data["observation"].shape[-1], "action_dim": data["action"].shape[-1]}
        if not background:
            self._monitor = make_monitor(spec, data, run_dir)
            return
        context = torch.multiprocessing.get_context("spawn")
        self._errors = context.SimpleQueue()
        # A daemon: a run that stops early (an error, Ctrl-C) does not wait for the fit.
        self._process = context.Process(target=_fit_monitor_in_child, daemon=True, args=(
            spec, data.cpu(), os.fspath(run_dir), self._errors, os.getpid()))
        self._process.start()

    def failed(self) -> bool:
        """Whether a background fit has already ended without its monitor (checked without waiting)."""
        return self._process is not None and not self._process.is_alive() and self._process.exitcode != 0

    def get(self) -> DeploymentMonitor:
        """The monitor; waits for a background fit, and raises :class:`MonitorError` if it failed."""
        if self._monitor is None:
            self._process.join()
            if self._process.exitcode != 0:
                reason = self._errors.get() if not self._errors.empty() else f"exit code {self._process.exitcode}"
                raise MonitorError(f"the deployment monitor's fit failed: {reason}")
            self._monitor = DeploymentMonitor.load(self.path, **self._sizes)
        return self._monitor
