"""Checks of a TELS recipe config, so a bad value fails at start-up with one clear message."""
from __future__ import annotations

import math
from typing import Any

__all__ = ["ConfigError", "validate_config"]


class ConfigError(ValueError):
    """A config value is out of range or of the wrong kind."""


def _number(cfg, path: str) -> float:
    value: Any = cfg
    for part in path.split("."):
        value = value[part]
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{path} must be a number, got {value!r}.") from None
    if not math.isfinite(number):
        raise ConfigError(f"{path} must be finite, got {value!r}.")
    return number


def validate_config(cfg) -> None:
    """Raises :class:`ConfigError` naming the first bad entry of a recipe config."""
    beta = cfg.tsidm.beta
    if beta != "auto":
        if _number(cfg, "tsidm.beta") < 0:
            raise ConfigError(f"tsidm.beta must be >= 0 or 'auto', got {beta!r}.")
    else:
        for value in cfg.tsidm.beta_candidates:
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"tsidm.beta_candidates must be finite numbers >= 0, got {value!r}.")
    for path in ("value.expectile",):
        if not 0.0 < _number(cfg, path) < 1.0:
            raise ConfigError(f"{path} must lie in (0, 1), got {_number(cfg, path)}.")
    if not 0.0 < _number(cfg, "value.target_update_rate") <= 1.0:
        raise ConfigError("value.target_update_rate must lie in (0, 1].")
    if not 0.0 < _number(cfg, "value.gamma") <= 1.0:
        raise ConfigError(f"value.gamma must lie in (0, 1], got {cfg.value.gamma}.")
    for path in ("tsidm.lr", "value.lr", "guide.lr", "guide.max_weight"):
        if _number(cfg, path) <= 0:
            raise ConfigError(f"{path} must be > 0, got {_number(cfg, path)}.")
    for path in ("guide.alpha", "guide.eta", "tsidm.weight_decay"):
        if _number(cfg, path) < 0:
            raise ConfigError(f"{path} must be >= 0, got {_number(cfg, path)}.")
    for path in ("dataset.reward_scale", "dataset.reward_bias"):
        _number(cfg, path)
    positive_ints = [
        "tsidm.batch_size", "tsidm.epochs", "optim.steps", "optim.batch_size", "eval.interval",
        "eval.episodes", "eval.last_n", "eval.max_steps", "logger.log_interval", "checkpoint.interval",
    ]
    for path in positive_ints + ["tsidm.steps", "dataset.size", "threads"]:
        value: Any = cfg
        for part in path.split("."):
            value = value[part]
        if value is None and path not in positive_ints:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ConfigError(f"{path} must be a positive integer, got {value!r}.")
    choices = {
        "tsidm.ablation": ("ae", "dyn", "ode", "full"),
        "tsidm.dim_reduction": ("sum", "mean"),
        "guide.mode": ("deterministic", "stochastic"),
        "dataset.subset": ("trajectories", "transitions"),
        "logger.wandb_mode": ("online", "offline", "disabled"),
    }
    for path, allowed in choices.items():
        section, key = path.split(".")
        if cfg[section][key] not in allowed:
            raise ConfigError(f"{path} must be one of {allowed}, got {cfg[section][key]!r}.")
