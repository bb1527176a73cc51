"""What the benchmark scripts share: launching the recipe, writing one result file, describing the machine.

Every script under ``benchmarks/`` is a module of this package and runs from the repository
root as ``python -m benchmarks.<script>`` (the reproduction study's as ``python -m study.<script>``),
so scripts import each other and this module by their package names.

* :func:`run_recipe` runs ``recipes/tels_offline.py`` in a subprocess with torch's threads
  pinned (``threads=`` and ``OMP_NUM_THREADS``), so a launcher never depends on what else runs.
* :func:`skip_existing` and :func:`write_result` give every result file the same life: a run
  whose file exists is skipped unless ``--force``, and a file appears whole (temp file + rename)
  or not at all, so a grid can be spread over jobs that check for each other's results;
  :func:`save_figure` writes a PNG the same way.
* :func:`portable` makes what is written into a result machine-independent: paths inside the
  repository become relative to its root and the interpreter becomes ``python``, so a committed
  JSON reads the same on every checkout.
* :func:`machine_description` is the one description of the machine a result records: runs on
  different CPUs differ in their numerics, so a same-seed comparison is only exact on one kind.
"""
from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "tels_offline.py"

__all__ = ["REPO", "RECIPE", "command_line", "invocation", "machine_description", "portable", "recorded_cpu",
           "repo_relative", "run_recipe", "save_figure", "skip_existing", "write_result"]


# ------------------------------------------------------------------ paths
def repo_relative(path: str | os.PathLike) -> str:
    """``path`` relative to the repository root if it lies inside it, else as given."""
    resolved = Path(path).resolve()
    try:
        return resolved.relative_to(REPO).as_posix()
    except ValueError:
        return str(path)


def write_generated(path: Path, text: str, command: str, check: bool = False) -> int:
    """Writes the generated document ``path`` (0), or with ``check`` compares it with ``text``: 0 when it is
    current, else 1, with the diff on stdout and the command that regenerates it on stderr."""
    if check:
        current = path.read_text() if path.exists() else ""
        if current == text:
            return 0
        import difflib

        sys.stdout.writelines(difflib.unified_diff(current.splitlines(True), text.splitlines(True),
                                                   path.name, f"{command} would write"))
        print(f"\n{path.name} is out of date: run {command}", file=sys.stderr)
        return 1
    path.write_text(text)
    print(f"wrote {repo_relative(path)}")
    return 0


def portable(value: Any) -> Any:
    """``value`` with every path inside the repository made relative to its root, every path beside it
    (``../shared/...``, a sibling folder of runs) relative to it too, and the running interpreter written
    ``python``; dicts, lists and tuples are converted throughout, so a command line or a hydra override
    (``run_dir=/abs/...``) is converted inside the string."""
    if isinstance(value, Path):
        return repo_relative(value)
    if isinstance(value, str):
        value = value.replace(sys.executable, "python")
        return value.replace(f"{REPO}{os.sep}", "").replace(f"{REPO.parent}{os.sep}", f"..{os.sep}")
    if isinstance(value, Mapping):
        return {key: portable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [portable(item) for item in value]
    return value


def command_line(cmd: Sequence[str]) -> str:
    """``cmd`` as one shell line, :func:`portable`."""
    return shlex.join(portable(list(cmd)))


def invocation() -> str:
    """The command line of this process as it is typed at the repository root
    (``python -m benchmarks.<script> ...`` for a script run as a module)."""
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    head = ["-m", spec.name] if spec is not None and spec.name else sys.argv[:1]
    return command_line([sys.executable, *head, *sys.argv[1:]])


def code_version() -> dict[str, Any]:
    """The commit the code of this checkout is at, and whether tracked files differ from it: part of a
    result's record, so that a run can be traced to the code that made it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}


# ---------------------------------------------------------------- running
def recipe_config(overrides: Sequence[str]):
    """The recipe's configuration as ``recipes/tels_offline.py`` composes it, with hydra ``overrides``."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "recipes" / "config"), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def with_pinned_precision(overrides: Sequence[str]) -> list[str]:
    """``overrides`` with ``precision=fp32`` unless they name a precision: the recorded results ran in fp32, and
    the recipe's default (``precision=auto``) would take bf16 on some CPUs."""
    return [*overrides, *([] if any(o.startswith("precision=") for o in overrides) else ["precision=fp32"])]


def run_recipe(overrides: Sequence[str], threads: int | None = None, *, quiet: bool = False) -> list[str]:
    """Runs ``recipes/tels_offline.py`` with ``overrides`` from the repository root; returns its command.

    With ``threads``, torch's intra-op threads (``threads=``) and OpenMP's (``OMP_NUM_THREADS``)
    are pinned to it. ``quiet`` hides the recipe's output unless it fails. A failure raises
    :class:`RuntimeError` naming the command.
    """
    cmd = [sys.executable, str(RECIPE), *with_pinned_precision(overrides)]
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
        if not any(o.startswith("threads=") for o in overrides):
            cmd.append(f"threads={threads}")
    if not quiet:
        print("$ " + command_line(cmd), flush=True)
    proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL if quiet else None,
                          stderr=subprocess.PIPE if quiet else None, text=True)
    if proc.returncode != 0:
        tail = f"\n{proc.stderr[-4000:]}" if quiet and proc.stderr else ""
        raise RuntimeError(f"the TELS recipe exited with code {proc.returncode}: {shlex.join(cmd)}{tail}")
    return cmd


# ---------------------------------------------------------------- results
def skip_existing(path: Path, force: bool) -> bool:
    """True (and says so) when the result ``path`` exists and ``force`` is off: its run is skipped."""
    if path.exists() and not force:
        print(f"skip: {repo_relative(path)} exists (--force to redo)", flush=True)
        return True
    return False


def write_result(path: Path, payload: Mapping[str, Any], force: bool = False) -> bool:
    """Writes ``payload`` as JSON to ``path``, made :func:`portable`, unless ``path`` exists and
    ``force`` is off (then nothing is written: the first result stays). True when written."""
    if skip_existing(path, force):
        return False
    from torchrl_tels.training import write_json  # temp file + rename: a skip check never sees half a file

    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, portable(payload))
    return True


def save_figure(fig, path: Path) -> Path:
    """Saves a matplotlib figure as a PNG at ``path``, written atomically as a result is."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
    fig.savefig(tmp, dpi=120)
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------- machine
def _cpu_model() -> str:
    """CPU model and widest AVX level, e.g. "AMD EPYC, AVX-512"."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or "unknown"
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")),
                 "unknown")
    return f"{model}, {'AVX-512' if ' avx512f' in info else 'AVX2' if ' avx2' in info else 'no AVX2'}"


def machine_description() -> dict[str, Any]:
    """What a score or a speed figure needs next to it: platform, CPU model and AVX level, CPU
    count, and the versions of Python, torch and torchrl."""
    import torch
    import torchrl

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
    }


def recorded_cpu(result: Mapping[str, Any]) -> str:
    """The CPU a result recorded: ``machine["cpu"]``, or the top-level ``cpu`` of older results."""
    return result.get("machine", {}).get("cpu") or result.get("cpu", "unknown")
