"""A finished run as standalone ``torch.export`` programs: the Eq. (11) actor and the deployment monitor.

The programs are traced from the library's own modules (:func:`~torchrl_tels.modules.load_tels_actor`,
:class:`~torchrl_tels.envs.DeploymentMonitor`), so they compute exactly what those do and load
with torch alone::

    policy = torch.export.load("runs/a/export/policy.pt2").module()
    action = policy(observation)                # (B, obs_dim) float32 -> (B, action_dim)
    monitor = torch.export.load("runs/a/export/monitor.pt2").module()
    recent, count = torch.zeros(B, window), torch.zeros(B, 1, dtype=torch.long)  # at each episode's start
    score, ood, window_mean, alarm, recent, count = monitor(observation, action, next_observation, recent, count)

:func:`export_run` refuses a folder that is not a finished run, or whose checkpoints do not belong
together, before anything is written; its files appear together, or not at all.
"""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_tels.checkpoint import file_sha256
from torchrl_tels.config import monitor_fit_options
from torchrl_tels.data import load_dataset
from torchrl_tels.envs import make_eval_env, DeploymentMonitor
from torchrl_tels.envs.monitor import SCORE_KEY
from torchrl_tels.errors import CheckpointError, MonitorError
from torchrl_tels.modules import load_tels_actor, TSIDM
from torchrl_tels.run_folder import RunFolder

__all__ = ["MonitorProgram", "PolicyProgram", "export_run", "onnx_missing"]

POLICY_FILE, MONITOR_FILE, MANIFEST_FILE = "policy.pt2", "monitor.pt2", "export.json"


class PolicyProgram(nn.Module):
    """observation → action through a TELS actor (Eq. 11), in deterministic mode, as one tensor function.

    The actor is the tensordict chain of :func:`~torchrl_tels.modules.make_tels_actor` (state
    normalization, :math:`\\phi_s`, the guide, the re-encoding option, :math:`\\psi_a(h_{inv}(\\cdot))`,
    clipping); this wrapper only moves a tensor in and out of a tensordict.
    """

    def __init__(self, actor, observation_key="observation", action_key="action") -> None:
        super().__init__()
        self.actor = actor.eval().requires_grad_(False)
        self.observation_key, self.action_key = observation_key, action_key

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({self.observation_key: observation}, batch_size=observation.shape[:-1])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.actor(td)[self.action_key]


class MonitorProgram(nn.Module):
    """One step of a calibrated deployment monitor as a tensor function.

    (observation, action, next observation, ``recent``, ``count``) → (``ood_score``, ``ood``,
    ``ood_window``, ``ood_alarm``, new ``recent``, new ``count``): the per-transition score and flag,
    and the windowed mean and its alarm. ``recent`` (B, window) and ``count`` (B, 1, int64) carry the
    episode's last scores from one call to the next; zeros start an episode.
    """

    def __init__(self, monitor: DeploymentMonitor) -> None:
        super().__init__()
        if not monitor.calibrated:
            raise CheckpointError("the deployment monitor is not calibrated; calibrate it before exporting.")
        self.monitor = monitor.eval()

    def forward(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor,
                recent: torch.Tensor, count: torch.Tensor):
        # No input checks in a traced program: they are data-dependent branches.
        monitor = self.monitor
        score = monitor.scores(observation, action, next_observation, check=False)[SCORE_KEY]
        window, recent, count = monitor.update_window(recent, count, score)
        return (score, monitor.is_ood(score, check=False), window, window > monitor.window_threshold,
                recent, count)


def onnx_missing() -> str | None:
    """What is missing for ONNX files (``torch.onnx``'s exporter needs ``onnx`` and ``onnxscript``), or ``None``."""
    missing = [name for name in ("onnx", "onnxscript") if importlib.util.find_spec(name) is None]
    return f"{' and '.join(missing)} not installed" if missing else None


def _read_results(folder: RunFolder) -> dict:
    payload = folder.read_results()
    if not payload.get("env"):
        raise CheckpointError(f"{folder.results_path} does not name the run's environment ('env').")
    return payload


def _check_same_task(monitor: DeploymentMonitor, results: dict, path: Path) -> None:
    dataset = monitor.metadata.get("dataset")
    if dataset is not None and results.get("dataset") is not None and dataset != results["dataset"]:
        raise CheckpointError(f"{path} was fitted to {dataset!r}, but the run trained on {results['dataset']!r}; "
                              "fit a monitor to the run's data with --calibrate DATASET.")


def _export(module: nn.Module, example: tuple[torch.Tensor, ...]) -> torch.export.ExportedProgram:
    batch = torch.export.Dim("batch")
    return torch.export.export(module, example, dynamic_shapes=tuple({0: batch} for _ in example))


def fit_monitor(dataset: str, quantile: float, folder: RunFolder, observation_dim: int,
                action_dim: int) -> DeploymentMonitor:
    """A monitor fitted to ``dataset`` with the run's ``monitor`` settings (its ``config.yaml``), cross-fitted.

    The sizes and the quantile are checked before the (minutes-long) fit."""
    if not 0.0 < float(quantile) < 1.0:
        raise MonitorError(f"--quantile must lie in (0, 1), got {quantile}.")
    data = load_dataset(dataset)
    for key, size in (("observation", observation_dim), ("action", action_dim)):
        if data[key].shape[-1] != size:
            raise MonitorError(f"{dataset}: its {key}s have size {data[key].shape[-1]}, but the run's environment's "
                               f"have size {size}: it is another task's data.")
    settings = folder.read_config().get("monitor") if folder.config_path.is_file() else None
    options = {} if settings is None else {"folds": settings["folds"], **monitor_fit_options(settings)}
    monitor = DeploymentMonitor.cross_fit(data, quantile=quantile, **options)
    monitor.metadata["dataset"] = str(dataset)
    return monitor


def export_run(
    run_dir: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    onnx: bool = False,
    calibrate: str | None = None,
    quantile: float = 0.99,
    log: Callable[[str], Any] = print,
) -> dict[str, Path]:
    """Writes ``policy.pt2`` (and ``monitor.pt2``, ``export.json``, ONNX files) of a finished run into ``out``.

    ``out`` defaults to ``run_dir/export``. The monitor is exported when ``run_dir/monitor.pt`` holds a
    calibrated one fitted to the run's dataset, or when ``calibrate`` names a dataset to fit one to
    (cross-fitted, flagging at ``quantile``; its ``monitor.pt`` then goes into ``out``). With ``onnx``, ``policy.onnx``/``monitor.onnx``
    are written too when the exporter's packages are installed (else ``log`` says so).

    Everything is checked and traced before ``out`` is touched; the files are written into a hidden
    sibling folder and moved into place, so a failure leaves ``out`` as it was (absent, if it was).
    Returns the written paths by file name.
    """
    folder = RunFolder.open_finished(run_dir, purpose="export")
    results = _read_results(folder)
    out = Path(out) if out is not None else folder.export_path
    if not out.parent.is_dir():
        raise CheckpointError(f"the folder {out.parent} for the export does not exist.")
    if out.exists() and not out.is_dir():
        raise CheckpointError(f"{out} exists and is not a folder.")

    env = make_eval_env(results["env"])
    observation_dim = int(env.observation_spec["observation"].shape[-1])
    action_dim = int(env.action_spec.shape[-1])
    tsidm = TSIDM.load(folder.tsidm_path, observation_dim=observation_dim, action_dim=action_dim)
    actor = load_tels_actor(folder.policy_path, tsidm, env.action_spec)

    monitor, monitor_source = None, None
    if calibrate is not None:
        monitor = fit_monitor(calibrate, quantile, folder, observation_dim, action_dim)
        monitor_source = str(calibrate)
    elif folder.monitor_path.is_file():
        monitor = DeploymentMonitor.load(folder.monitor_path, observation_dim=observation_dim,
                                         action_dim=action_dim)
        _check_same_task(monitor, results, folder.monitor_path)
        monitor_source = RunFolder.MONITOR
    else:
        log(f"no calibrated monitor in {folder.path} ({RunFolder.MONITOR}) and no --calibrate DATASET: exporting the "
            "policy only")

    observation = tsidm.obs_loc.expand(2, observation_dim).clone()
    programs = {POLICY_FILE: _export(PolicyProgram(actor), (observation,))}
    if monitor is not None:
        action = torch.zeros(2, action_dim)
        # distinct tensors: an input passed twice would be traced as one
        recent, count = torch.zeros(2, monitor.window), torch.zeros(2, 1, dtype=torch.long)
        programs[MONITOR_FILE] = _export(MonitorProgram(monitor),
                                         (observation, action, observation.clone(), recent, count))
    want_onnx = onnx and (reason := onnx_missing()) is None
    if onnx and not want_onnx:
        log(f"--onnx: {reason}; skipping the ONNX files (pip install onnx onnxscript)")

    low, high = env.action_spec.low, env.action_spec.high
    manifest = {
        "env": results["env"],
        "observation_dim": observation_dim,
        "action_dim": action_dim,
        "action_low": low.tolist(),
        "action_high": high.tolist(),
        "inputs": {"policy": "observation (B, observation_dim) float32 -> action (B, action_dim)",
                   "monitor": "observation, action, next_observation (B, .) float32, recent (B, window) float32, "
                              "count (B, 1) int64 (zeros at an episode's start) -> ood_score (B,), ood (B,) bool, "
                              "ood_window (B,), ood_alarm (B,) bool, recent, count"},
        "sources": {path.name: file_sha256(path) for path in (folder.tsidm_path, folder.policy_path)},
        "monitor": None if monitor is None else {
            "score": monitor.score_key, "combine": list(monitor.combine), "threshold": float(monitor.threshold),
            "quantile": float(monitor.quantile), "window": monitor.window,
            "window_threshold": float(monitor.window_threshold), "window_quantile": float(monitor.window_quantile),
            "calibration": monitor.metadata.get("calibration"), "calibrated_from": monitor_source},
        "torch": torch.__version__,
    }

    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        umask = os.umask(0)
        os.umask(umask)
        staging.chmod(0o777 & ~umask)  # mkdtemp makes it private; the export folder is an ordinary one
        for name, program in programs.items():
            torch.export.save(program, staging / name)
            if want_onnx:
                torch.onnx.export(program, f=str(staging / Path(name).with_suffix(".onnx")), dynamo=True)
        if calibrate is not None:
            monitor.save(staging / RunFolder.MONITOR, metadata={"dataset": str(calibrate)})
        (staging / MANIFEST_FILE).write_text(json.dumps(manifest, indent=2))
        written = sorted(path.name for path in staging.iterdir())
        if not out.exists():
            os.replace(staging, out)  # the whole folder appears at once
        else:
            for name in written:
                os.replace(staging / name, out / name)
            staging.rmdir()
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {name: out / name for name in written}
