"""A TELS recipe config: its checks, so a bad value fails at start-up with one clear message, and the typed
:class:`RunSpec` the recipe builds from it once, with the device, precision and threads resolved.

This is the one module of the package that reads a hydra/omegaconf config."""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from omegaconf import OmegaConf

from torchrl_tels.data.subsets import SUBSET_MODES
from torchrl_tels.errors import ConfigError

__all__ = [
    "CheckpointSpec",
    "CompileSpec",
    "ConfigError",
    "DatasetSpec",
    "DiagnosticsSpec",
    "EvalSpec",
    "GuideSpec",
    "LoggerSpec",
    "MonitorSpec",
    "PolicySpec",
    "RunSpec",
    "TSIDMSpec",
    "ValueSpec",
    "RESUMABLE_KEYS",
    "STAGE1_KEYS",
    "check_precision_supported",
    "resolve_precision",
    "check_folder_creatable",
    "check_same_run",
    "check_writable_folder",
    "stage1_differences",
    "training_config",
    "resolve_device",
    "monitor_fit_options",
    "available_cpus",
    "resolve_threads",
    "validate_config",
]

#: Top-level config entries that may differ between a run and its ``resume=true``
#: continuation: they decide where and how a run is logged, not what it computes. The deployment
#: monitor is fitted once and saved as monitor.pt, which a continuation reads back.
RESUMABLE_KEYS = ("run_dir", "resume", "overwrite", "threads", "device", "logger", "checkpoint", "compile", "monitor",
                  "diagnostics")

#: Options added after checkpoints were first written, as (section, key): (the value that
#: reproduces how a checkpoint without the option behaved, when the option matters at all).
#: An older checkpoint is compared as if it held that value, or the current one where the
#: option has no effect, so runs made before an option existed still resume.
ADDED_OPTIONS = {
    ("tsidm", "beta_selection"): ("weighted", lambda cfg: cfg.get("tsidm", {}).get("beta") == "auto"),
    ("tsidm", "term_weights"): (None, lambda cfg: True),
    ("eval", "batched"): (False, lambda cfg: True),
    ("guide", "reach_weight"): (0.0, lambda cfg: True),
    ("tsidm", "warn_steps"): (None, lambda cfg: False),  # a warning's threshold: changes nothing a run computes
}


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


def _check_deletion(cfg) -> None:
    boxes = cfg.dataset.delete_boxes
    if isinstance(boxes, (str, bytes)) or not hasattr(boxes, "__len__"):
        raise ConfigError(f"dataset.delete_boxes must be a list of [xmin, xmax, ymin, ymax] boxes, got {boxes!r}.")
    for box in boxes:
        ok = (not isinstance(box, (str, bytes)) and hasattr(box, "__len__") and len(box) == 4
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in box))
        if not ok or box[0] > box[1] or box[2] > box[3]:
            raise ConfigError(f"dataset.delete_boxes: each box must be [xmin, xmax, ymin, ymax] with finite "
                              f"numbers, xmin <= xmax and ymin <= ymax; got {box!r}.")
    if not 0.0 <= _number(cfg, "dataset.delete_ratio") <= 1.0:
        raise ConfigError(f"dataset.delete_ratio must lie in [0, 1], got {cfg.dataset.delete_ratio}.")
    xy = cfg.dataset.delete_xy
    if (isinstance(xy, (str, bytes)) or not hasattr(xy, "__len__") or len(xy) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in xy)):
        raise ConfigError(f"dataset.delete_xy must be two observation column indices >= 0, got {xy!r}.")


def _check_term_weights(cfg) -> None:
    weights = cfg.tsidm.term_weights
    if weights is None:
        return
    if not hasattr(weights, "items") or not set(weights) <= {"dyn", "ode", "tsym"}:
        raise ConfigError(f"tsidm.term_weights must be null or a mapping with keys among dyn, ode, tsym, "
                          f"got {weights!r}.")
    for name in weights:
        if _number(cfg, f"tsidm.term_weights.{name}") < 0:
            raise ConfigError(f"tsidm.term_weights.{name} must be >= 0, got {weights[name]!r}.")


def available_cpus() -> int:
    """The logical CPUs this process may run on: its affinity (what a SLURM job or ``taskset`` grants), not
    the whole machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # platforms without sched_getaffinity
        return os.cpu_count() or 1


def resolve_threads(spec) -> int:
    """torch's intra-op thread count for ``threads``: ``auto`` (or ``None``) is half the CPUs this process may
    use (:func:`available_cpus`), at least 1. Beside another busy process, torch's default of every core ran
    stage 1 several times slower than one thread (BENCHMARKS.md, "CPU threads"); half leaves a neighbour its
    share."""
    if spec is None or spec == "auto":
        return max(1, available_cpus() // 2)
    return int(spec)


def resolve_device(spec: str) -> "torch.device":
    """The device ``spec`` names: ``auto`` (CUDA where available, else the CPU), ``cpu``, ``cuda`` or
    ``cuda:N``; a :class:`ConfigError` for anything else, or for CUDA on a machine without it."""
    import torch

    spec = str(spec)
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if spec != "cpu" and not (spec == "cuda" or (spec.startswith("cuda:") and spec[5:].isdigit())):
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N, got {spec!r}.")
    device = torch.device(spec)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device={spec} but this machine has no CUDA device (torch {torch.__version__}); "
                              f"use device=cpu or device=auto.")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(f"device={spec} but this machine has {torch.cuda.device_count()} CUDA device(s).")
    return device


def validate_config(cfg) -> None:
    """Raises :class:`ConfigError` naming the first bad entry of a recipe config."""
    resolve_device(cfg.device)
    for key in ("resume", "overwrite"):
        value = cfg.get(key, False)
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}.")
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
    for path in ("guide.alpha", "guide.eta", "guide.tsym_weight", "guide.reach_weight", "tsidm.weight_decay"):
        if _number(cfg, path) < 0:
            raise ConfigError(f"{path} must be >= 0, got {_number(cfg, path)}.")
    for path in ("dataset.reward_scale", "dataset.reward_bias"):
        _number(cfg, path)
    _check_deletion(cfg)
    _check_term_weights(cfg)
    for path in ("eval.batched", "guide.tsym_regularizer", "guide.tsym_relative", "guide.reencode_proposal", "guide.act_with_dropout"):
        if not isinstance(OmegaConf.select(cfg, path), bool):
            raise ConfigError(f"{path} must be true or false, got {OmegaConf.select(cfg, path)!r}.")
    if beta == "auto" and len(cfg.tsidm.beta_candidates) == 0:
        raise ConfigError("tsidm.beta=auto needs at least one value in tsidm.beta_candidates.")
    if not 0.0 <= _number(cfg, "tsidm.inverse_dropout") < 1.0:
        raise ConfigError(f"tsidm.inverse_dropout must lie in [0, 1), got {cfg.tsidm.inverse_dropout}.")
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int) or cfg.seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {cfg.seed!r}.")
    _check_seeds(cfg)
    cells = [f"tsidm.{name}_cells" for name in ("encoder", "decoder", "inverse", "action_decoder", "dynamics")]
    for path in cells + ["value.num_cells", "guide.num_cells"]:
        section, key = path.split(".")
        value = cfg[section][key]
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or not all(
            isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value
        ):
            raise ConfigError(f"{path} must be a list of positive integers (layer widths), got {value!r}.")
    positive_ints = [
        "tsidm.batch_size", "tsidm.epochs", "policy.steps", "policy.batch_size", "eval.interval",
        "eval.episodes", "eval.last_n", "eval.max_steps", "logger.log_interval", "checkpoint.interval",
    ]
    optional = ["tsidm.steps", "tsidm.latent_state_dim", "tsidm.latent_action_dim", "dataset.size"]
    if cfg.threads is not None and cfg.threads != "auto":
        optional.append("threads")
    for path in positive_ints + optional:
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
        "tsidm.latent_scale": ("free", "relative", "standardized"),
        "tsidm.beta_selection": ("unweighted", "weighted"),
        "guide.mode": ("deterministic", "stochastic"),
        "dataset.subset": SUBSET_MODES,
        "logger.wandb_mode": ("online", "offline", "disabled"),
        "precision": ("auto", "fp32", "bf16"),
    }
    for path, allowed in choices.items():
        value = OmegaConf.select(cfg, path)
        if value not in allowed:
            raise ConfigError(f"{path} must be one of {allowed}, got {value!r}.")
    _check_compile(cfg)
    _check_monitor(cfg)
    if cfg.guide.mode == "stochastic" and _number(cfg, "guide.reach_weight") > 0:
        raise ConfigError("guide.reach_weight applies to the deterministic guide (Eq. 9) only; "
                          "guide.mode=stochastic needs guide.reach_weight=0.")


def monitor_fit_options(settings) -> dict:
    """The keywords of ``DeploymentMonitor.fit``/``cross_fit`` that a run's ``monitor`` group (a config or a
    plain mapping, as a finished run's ``config.yaml`` reads) sets, besides the calibration scheme and the flag
    quantile."""
    return {"members": settings["members"], "num_cells": tuple(settings["num_cells"]), "steps": settings["steps"],
            "window": settings["window"], "window_quantile": settings["window_quantile"]}


def _check_monitor(cfg) -> None:
    monitor = OmegaConf.select(cfg, "monitor")
    if monitor is None:
        raise ConfigError("the config has no 'monitor' group (the deployment monitor's settings).")
    if monitor.calibration not in ("cross_fit", "split"):
        raise ConfigError(f"monitor.calibration must be one of ('cross_fit', 'split'), got {monitor.calibration!r}.")
    for key, low in (("folds", 2), ("members", 1), ("steps", 1), ("window", 1)):
        value = monitor[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"monitor.{key} must be an integer >= {low}, got {value!r}.")
    cells = monitor.num_cells
    if isinstance(cells, (str, bytes)) or not hasattr(cells, "__len__") or not all(
            isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in cells):
        raise ConfigError(f"monitor.num_cells must be a list of positive integers (layer widths), got {cells!r}.")
    if monitor.get("background", False) not in ("auto", True, False):
        raise ConfigError(f"monitor.background must be auto, true or false, got {monitor.get('background')!r}.")
    for key, node in (("monitor.max_transitions", monitor), ("diagnostics.max_transitions",
                                                            OmegaConf.select(cfg, "diagnostics") or {})):
        value = node.get("max_transitions")
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 100):
            raise ConfigError(f"{key} must be null or an integer >= 100, got {value!r}.")
    for key in ("holdout", "quantile", "window_quantile"):
        if not 0.0 < _number(cfg, f"monitor.{key}") < 1.0:
            raise ConfigError(f"monitor.{key} must lie in (0, 1), got {monitor[key]!r}.")


def _check_compile(cfg) -> None:
    from torchrl_tels.compile import COMPILE_MODES

    for path in ("compile.compile", "compile.cudagraphs"):
        if not isinstance(OmegaConf.select(cfg, path), bool):
            raise ConfigError(f"{path} must be true or false, got {OmegaConf.select(cfg, path)!r}.")
    if cfg.compile.mode not in COMPILE_MODES:
        raise ConfigError(f"compile.mode must be one of {COMPILE_MODES}, got {cfg.compile.mode!r}.")
    if cfg.compile.cudagraphs and resolve_device(cfg.device).type != "cuda":
        raise ConfigError(f"compile.cudagraphs=true records CUDA graphs, but the run computes on "
                          f"{resolve_device(cfg.device)} (device={cfg.device}); use compile.cudagraphs=false "
                          f"or a CUDA device.")


def native_bf16_supported() -> bool:
    """Whether this CPU multiplies bf16 matrices natively (AVX512-BF16 or AMX), as oneDNN reports it."""
    import torch

    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def resolve_precision(spec: str, device: str = "cpu") -> str:
    """The precision ``spec`` names: ``fp32``, ``bf16``, or for ``auto`` bf16 where the run computes on a
    CPU that multiplies bf16 natively (AMX or AVX512-BF16) and fp32 everywhere else.

    On such a CPU bf16 halves a step at the recipe's widths and scored as fp32 in paired runs
    (BENCHMARKS.md, "bf16 on a CPU that has it"); elsewhere bf16 is emulated, or on a GPU not measured."""
    if spec != "auto":
        return str(spec)
    return "bf16" if resolve_device(device).type == "cpu" and native_bf16_supported() else "fp32"


def check_precision_supported(precision: str, device: str = "cpu") -> None:
    """Raises :class:`ConfigError` for ``precision=bf16`` where the device has no native bf16.

    On a CPU without it, autocast emulates bf16 and a TELS step runs tens of
    times slower than fp32 (BENCHMARKS.md), so the request is refused, not obeyed;
    on CUDA, bf16 needs a GPU that supports it (``torch.cuda.is_bf16_supported``).
    """
    if precision != "bf16":
        return
    import torch

    if resolve_device(device).type == "cuda":
        if not torch.cuda.is_bf16_supported():
            raise ConfigError(f"precision=bf16 but the GPU of device={device} does not support bf16. "
                              f"Use precision=fp32.")
        return
    if not native_bf16_supported():
        raise ConfigError(
            f"precision=bf16 needs a CPU with native bf16 matrix multiplication (AVX512-BF16 or AMX); "
            f"this one offers {torch.backends.cpu.get_cpu_capability()}, where bf16 autocast is emulated and "
            f"runs tens of times slower than fp32. Use precision=fp32."
        )


def _check_seeds(cfg) -> None:
    seeds = cfg.get("seeds")
    if seeds is None:
        return
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__len__") or len(seeds) == 0 or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds
    ):
        raise ConfigError(f"seeds must be a non-empty list of integers >= 0 (or null), got {seeds!r}.")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds must not repeat a seed, got {list(seeds)}.")
    # Stacked seeds share the loss modules' plain attributes (torchrl_tels.seeds): options that
    # give each seed its own value of one cannot be stacked.
    if cfg.tsidm.beta == "auto":
        raise ConfigError("seeds: tsidm.beta=auto picks beta per run; give tsidm.beta a number, or run the "
                          "seeds one by one with seed=<k>.")
    if cfg.guide.mode == "stochastic" and cfg.guide.tsym_regularizer:
        raise ConfigError("seeds: guide.mode=stochastic samples its T-symmetry proposal in place, which the "
                          "stacked (vmapped) update cannot do; run the seeds one by one with seed=<k>.")
    if cfg.guide.tsym_relative:
        raise ConfigError("seeds: guide.tsym_relative=true scales each seed's guide by its own data step; run "
                          "the seeds one by one with seed=<k>.")


def training_config(cfg) -> dict:
    """The resolved config without :data:`RESUMABLE_KEYS`: what a run's checkpoints were made with.

    Plain ``dict``/``list``/scalars, so it travels in a ``weights_only`` checkpoint.
    """
    from omegaconf import DictConfig, OmegaConf

    container = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    # ``seeds`` came later; a single-seed run (null) records it as absent, as its older checkpoints do.
    return {key: value for key, value in container.items()
            if key not in RESUMABLE_KEYS and not (key == "seeds" and value is None)}


def _differences(saved: Any, current: Any, prefix: str = "") -> list[str]:
    if isinstance(saved, Mapping) and isinstance(current, Mapping):
        out = []
        for key in sorted(set(saved) | set(current), key=str):
            path = f"{prefix}.{key}" if prefix else str(key)
            out += _differences(saved.get(key, "<absent>"), current.get(key, "<absent>"), path)
        return out
    return [] if saved == current else [f"{prefix}: {saved!r} -> {current!r}"]


#: What decides stage 1, the TS-IDM: a run may start stage 2 from another run's TS-IDM
#: (``tsidm.checkpoint``) as if it had trained it itself only when these agree. Like
#: :data:`RESUMABLE_KEYS`, ``device``, ``threads`` and ``compile`` are left out: they change a step's
#: rounding, not what it computes.
STAGE1_KEYS = ("seed", "precision", "dataset", "tsidm")
#: Entries of :data:`STAGE1_KEYS` that stage 1 never reads: where the TS-IDM came from, a warning's
#: threshold, and the rewards (the TS-IDM models states and actions; the rewards enter at stage 2).
STAGE1_UNREAD = {"tsidm": ("checkpoint", "warn_steps"), "dataset": ("reward_scale", "reward_bias")}


def stage1_differences(saved: Mapping, current: Mapping) -> list[str]:
    """What differs between two :func:`training_config` records in the settings of stage 1
    (:data:`STAGE1_KEYS` less :data:`STAGE1_UNREAD`), as ``"key: saved -> current"``."""

    def stage1(config: Mapping) -> dict:
        picked = {key: config.get(key) for key in STAGE1_KEYS}
        for section, unread in STAGE1_UNREAD.items():
            picked[section] = {k: v for k, v in (picked[section] or {}).items() if k not in unread}
        return picked

    return _differences(stage1(_with_added_options(saved, current)), stage1(current))


def _with_added_options(saved: Mapping, current: Mapping) -> Mapping:
    """``saved`` with every :data:`ADDED_OPTIONS` entry it lacks filled in (see there)."""
    filled = {key: dict(value) if isinstance(value, Mapping) else value for key, value in saved.items()}
    for (section, key), (legacy, matters) in ADDED_OPTIONS.items():
        if isinstance(filled.get(section), dict) and key not in filled[section]:
            if matters(saved):
                filled[section][key] = legacy
            elif key in current.get(section, {}):
                filled[section][key] = current[section][key]
    return filled


def check_same_run(saved: Mapping | None, current: Mapping, where: str) -> None:
    """Raises :class:`ConfigError` if a checkpoint's :func:`training_config` differs from ``current``.

    A checkpoint from a run with another dataset, task, network size or
    hyperparameter cannot be continued: the message names what changed.
    ``saved=None`` (a checkpoint that predates this record) is accepted.
    """
    if saved is None:
        return
    saved = _with_added_options(saved, current)
    differences = _differences(saved, current)
    if differences:
        shown = "; ".join(differences[:4]) + (f"; and {len(differences) - 4} more" if len(differences) > 4 else "")
        raise ConfigError(
            f"{where} was made by a run with another config ({shown}); resume=true needs the "
            f"same settings (only {', '.join(RESUMABLE_KEYS)} may change), or choose a new run_dir."
        )


def check_folder_creatable(folder: str | os.PathLike, name: str = "run_dir") -> Path:
    """Checks, without creating anything, that ``folder`` exists writable or can be created."""
    folder = Path(folder).absolute()
    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if existing is None or not existing.is_dir():
        raise ConfigError(f"{name} {folder} is not writable: Not a directory.")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{name} {folder} is not writable: Permission denied.")
    return folder


def check_writable_folder(folder: str | os.PathLike, name: str = "run_dir") -> Path:
    """Creates ``folder`` and checks a file can be written in it; :class:`ConfigError` if not."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise ConfigError(f"{name} {folder} is not writable: {err.strerror or err}.") from None
    return folder


# ----------------------------------------------------------------------------- the run spec
# The recipe's config as typed records, built once at the recipe's boundary (:meth:`RunSpec.from_config`); the
# library below reads these and never a DictConfig. Each section mirrors a group of ``recipes/config/config.yaml``
# (its comments say what each entry means); a field with a default is one added after runs were first saved, and
# the default reproduces how such a run behaved.


@dataclass(frozen=True)
class DatasetSpec:
    name: str
    task: str | None
    size: int | None
    subset: str
    reward_scale: float
    reward_bias: float
    delete_boxes: list
    delete_ratio: float
    delete_xy: list


@dataclass(frozen=True)
class TSIDMSpec:
    checkpoint: str | None
    beta: float | str  # a number, or "auto": App. B.5's choice among ``beta_candidates``
    beta_candidates: list
    ablation: str
    epochs: int
    steps: int | None
    batch_size: int
    lr: float
    weight_decay: float
    latent_state_dim: int | None
    latent_action_dim: int | None
    inverse_dropout: float
    encoder_cells: list
    decoder_cells: list
    inverse_cells: list
    action_decoder_cells: list
    dynamics_cells: list
    dim_reduction: str
    latent_scale: str
    beta_selection: str = "weighted"
    term_weights: dict | None = None
    warn_steps: int | None = None


@dataclass(frozen=True)
class ValueSpec:
    expectile: float
    gamma: float
    target_update_rate: float
    lr: float
    num_cells: list


@dataclass(frozen=True)
class GuideSpec:
    mode: str
    alpha: float
    eta: float
    tsym_regularizer: bool
    tsym_weight: float
    tsym_relative: bool
    max_weight: float
    reencode_proposal: bool
    act_with_dropout: bool
    lr: float
    num_cells: list
    reach_weight: float = 0.0


@dataclass(frozen=True)
class PolicySpec:
    steps: int
    batch_size: int


@dataclass(frozen=True)
class MonitorSpec:
    calibration: str
    folds: int
    holdout: float
    members: int
    num_cells: list
    steps: int
    window: int
    quantile: float
    window_quantile: float
    background: bool | str = False
    max_transitions: int | None = None

    def settings(self) -> dict:
        """What the monitor is fitted with, as ``monitor.pt`` records it (all but where it is fitted)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "background"}


@dataclass(frozen=True)
class DiagnosticsSpec:
    max_transitions: int | None = None


@dataclass(frozen=True)
class EvalSpec:
    interval: int
    episodes: int
    last_n: int
    max_steps: int
    batched: bool = False


@dataclass(frozen=True)
class LoggerSpec:
    exp_name: str
    wandb_mode: str
    project: str
    log_interval: int


@dataclass(frozen=True)
class CheckpointSpec:
    interval: int


@dataclass(frozen=True)
class CompileSpec:
    """:func:`~torchrl_tels.compile.compile_update`'s switches; all off for a run saved before they existed."""

    compile: bool = False
    cudagraphs: bool = False
    mode: str | None = None


@dataclass(frozen=True)
class RunSpec:
    """One run of the recipe, resolved: where it computes (``device``, ``threads``), in what ``precision``, and
    every section of its config as a typed record.

    ``config`` is the resolved config as plain containers (``precision`` resolved), which ``config.yaml``
    (``yaml``), the logger and the resume check (:func:`training_config`) record.
    """

    seed: int
    seeds: list | None
    device: "torch.device"
    precision: str
    threads: int
    run_dir: Path
    resume: bool
    overwrite: bool
    dataset: DatasetSpec
    tsidm: TSIDMSpec
    value: ValueSpec
    guide: GuideSpec
    policy: PolicySpec
    monitor: MonitorSpec
    diagnostics: DiagnosticsSpec
    eval: EvalSpec
    logger: LoggerSpec
    checkpoint: CheckpointSpec
    compile: CompileSpec
    config: dict
    yaml: str

    SECTIONS = {"dataset": DatasetSpec, "tsidm": TSIDMSpec, "value": ValueSpec, "guide": GuideSpec,
                "policy": PolicySpec, "monitor": MonitorSpec, "diagnostics": DiagnosticsSpec, "eval": EvalSpec,
                "logger": LoggerSpec, "checkpoint": CheckpointSpec, "compile": CompileSpec}

    @classmethod
    def from_config(cls, cfg, *, validate: bool = True) -> "RunSpec":
        """The spec of a recipe config (a DictConfig or plain mapping). ``validate`` checks it first
        (:func:`validate_config`, :func:`check_precision_supported`), as the recipe does; without it, as for the
        ``config.yaml`` of a finished run, an entry the config lacks reads as its default, or ``None``."""
        from omegaconf import DictConfig

        if validate:
            validate_config(cfg)
        container = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
        device = container.get("device", "auto")
        container["precision"] = resolve_precision(container.get("precision", "auto"), device)
        if validate:
            check_precision_supported(container["precision"], device)
        return cls._build(container)

    @classmethod
    def _build(cls, container: dict) -> "RunSpec":
        sections = {name: _section(section, container.get(name) or {}) for name, section in cls.SECTIONS.items()}
        return cls(seed=container.get("seed"), seeds=container.get("seeds"),
                   device=resolve_device(container.get("device", "auto")), precision=container["precision"],
                   threads=resolve_threads(container.get("threads", "auto")),
                   run_dir=Path(str(container.get("run_dir"))).absolute(), resume=bool(container.get("resume")),
                   overwrite=bool(container.get("overwrite")), config=container,
                   yaml=OmegaConf.to_yaml(OmegaConf.create(container)), **sections)

    def for_seed(self, seed: int, run_dir: str | os.PathLike) -> "RunSpec":
        """The spec of one seed of a ``seeds`` run: what that seed's own run, writing to ``run_dir``, would get."""
        return self._build({**self.config, "seed": seed, "seeds": None, "run_dir": str(run_dir)})

    def precision_context(self):
        """The factory of the loss forward passes' autocast context on this run's device and precision."""
        from torchrl_tels.compile import precision_context

        return precision_context(self.device, self.precision)


def _section(section: type, node: Mapping):
    """``section`` from a config group; an entry the group lacks takes the field's default, else ``None``."""
    values = {}
    for f in dataclasses.fields(section):
        default = f.default if f.default is not dataclasses.MISSING else None
        values[f.name] = node.get(f.name, default)
    return section(**values)
