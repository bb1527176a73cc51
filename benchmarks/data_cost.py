"""What a recipe run costs as the data grows: monitor fit, after-training readings, whole run, peak memory, steps/s.

Data: the 100k HalfCheetah-v5 SAC set (``../shared/datasets/halfcheetah-v5-sac/medium-100k.npz``); a size
below it keeps its first whole episodes, a size above it tiles the set with Gaussian noise (1 % of each
observation entry's std) on every copy after the first, so the tiled 1M set is generated here, never
committed. Each size runs the default recipe in a subprocess with short stages (``--steps`` each) and one
torch thread, and records the run's own timings (``wall_time_s``) and its peak resident memory (the
child's ``ru_maxrss``)::

    python -m benchmarks.data_cost --sizes 10000 100000 1000000 --steps 300 --threads 1
    python -m benchmarks.data_cost --table

writes ``benchmarks/results/data_cost/size<N>.json``; ``--table`` prints the table from them.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import invocation, machine_description, recorded_cpu, REPO, RECIPE, write_result
from torchrl_tels.run_folder import RunFolder

OUT = REPO / "benchmarks" / "results" / "data_cost"
TASK = "mujoco/halfcheetah/medium-v0"


def source() -> Path:
    from torchrl_tels.data import shared_datasets_dir

    shared = shared_datasets_dir()
    if shared is None:
        raise SystemExit("error: ../shared/datasets is absent: the data-cost benchmark needs the 100k HalfCheetah set.")
    return shared / "halfcheetah-v5-sac" / "medium-100k.npz"


def make_set(size: int, path: Path, seed: int = 0) -> int:
    """Writes a D4RL-style ``.npz`` of ``size`` transitions (see the module docstring); returns its length."""
    with np.load(source()) as raw:
        arrays = {key: raw[key] for key in raw.files}
    n = len(arrays["observations"])
    rng = np.random.default_rng(seed)
    if size <= n:
        ends = np.flatnonzero(arrays.get("timeouts", np.zeros(n, bool)) | arrays["terminals"])
        cut = next((int(e) + 1 for e in ends if e + 1 >= size), n)
        out = {key: value[:cut] for key, value in arrays.items()}
    else:
        copies = -(-size // n)
        scale = 0.01 * arrays["observations"].std(0)
        out = {}
        for key, value in arrays.items():
            parts = [value]
            for _ in range(copies - 1):
                part = value.copy()
                if key in ("observations", "next_observations"):
                    part = part + (rng.standard_normal(part.shape) * scale).astype(part.dtype)
                parts.append(part)
            out[key] = np.concatenate(parts)[:size]
        # every copy ends an episode where the original does; the cut at `size` ends one more
        for flag in ("timeouts",):
            if flag in out:
                out[flag][-1] = True
    np.savez(path, **out)
    return len(out["observations"])


def run_size(size: int, steps: int, threads: int) -> dict:
    import subprocess

    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / f"halfcheetah-{size}.npz"
        transitions = make_set(size, data)
        run_dir = Path(tmp) / "run"
        cmd = [sys.executable, str(RECIPE), f"dataset.name={data}", f"dataset.task={TASK}", f"run_dir={run_dir}",
               f"threads={threads}", f"tsidm.steps={steps}", f"policy.steps={steps}", f"eval.interval={steps}",
               "eval.episodes=2", "logger.wandb_mode=disabled", "monitor.background=false"]  # the fit timed alone
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        elapsed = time.perf_counter() - start
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"error: the size-{size} run failed: {proc.stderr.read()[-2000:]}")
        results = RunFolder(run_dir).read_results()
    return {"size": transitions, "steps": steps, "threads": threads, "elapsed_s": elapsed,
            "peak_memory_gb": usage.ru_maxrss / 1024 ** 2, "wall_time_s": results["wall_time_s"],
            "steps_per_s": results["steps_per_s"], "command": invocation(), "machine": machine_description()}


def table(folder: Path = OUT) -> str:
    rows = sorted((json.loads(p.read_text()) for p in folder.glob("size*.json")), key=lambda r: r["size"])
    lines = ["| transitions | monitor fit | after-training readings | whole run | peak memory | TS-IDM steps/s "
             "| policy steps/s | machine |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w, s = r["wall_time_s"], r["steps_per_s"]
        lines.append(f"| {r['size']:,} | {w['monitor']:.0f} s | {w['diagnostics']:.1f} s | {r['elapsed_s']:.0f} s | "
                     f"{r['peak_memory_gb']:.2f} GB | {s['tsidm']:.1f} | {s['policy_excluding_eval']:.1f} | "
                     f"{recorded_cpu(r)}, {r['threads']} thread |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.data_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--steps", type=int, default=300, help="TS-IDM and policy steps each")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--table", action="store_true", help="print the table from the JSONs and exit")
    args = parser.parse_args(argv)
    if not args.table:
        for size in args.sizes:
            write_result(args.out / f"size{size}.json", run_size(size, args.steps, args.threads), force=args.force)
    print(table(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
