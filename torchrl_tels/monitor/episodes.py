"""The deployment monitor along evaluation episodes: what ``results.json`` records of it."""
from __future__ import annotations

import torch

from torchrl_tels.envs import DeploymentMonitor
from torchrl_tels.envs.monitor import running_mean
from torchrl_tels.errors import MonitorError

__all__ = ["monitor_record"]


def monitor_record(monitor: DeploymentMonitor, rollouts: list) -> dict:
    """The monitor along each episode: its score and windowed mean at every step, the fraction of flagged
    steps and of alarmed steps. A monitor error (a non-finite state) is recorded, not raised, so it never
    costs the finished training."""
    record = {"score": monitor.score_key, "threshold": float(monitor.threshold), "quantile": float(monitor.quantile),
              "window": monitor.window, "window_threshold": float(monitor.window_threshold),
              "window_quantile": float(monitor.window_quantile)}
    try:
        device = monitor.threshold.device
        scores = [monitor(rollout.to(device))["next", "ood_score"].reshape(-1).cpu() for rollout in rollouts]
    except MonitorError as err:
        return {**record, "error": str(err)}
    windows = [running_mean(score, monitor.window).float() for score in scores]
    flat, flat_windows = torch.cat(scores), torch.cat(windows)
    return {**record, "ood_fraction": (flat > monitor.threshold).float().mean().item(),
            "alarm_fraction": (flat_windows > monitor.window_threshold).float().mean().item(),
            "scores": [score.tolist() for score in scores], "windows": [window.tolist() for window in windows]}
