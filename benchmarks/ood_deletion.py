"""The OOD deletion test of the TELS paper (Fig. 3): delete data along the path, train, roll out.

For a maze dataset, the transitions whose (x, y) lies in regions along the
path from the evaluation start to the goal are deleted at a given ratio
(0 %, 70 %, 100 %), then TELS (``recipes/tels_offline.py``, ``domain=maze``) and
TorchRL's ``IQLLoss`` (the IQL paper's maze values) are trained on what is
left, with the same policy-step budget. Each trained policy is rolled out for
20 deterministic episodes from the fixed start; the result JSON keeps the
success rate and every (x, y) path. Run from the repository root::

    python -m benchmarks.ood_deletion --setup pointmaze-medium --method tels --ratio 0.7 --seed 0
    python -m benchmarks.ood_deletion --grid --threads 1     # every missing (setup, method, ratio, seed)
    python -m benchmarks.ood_deletion --list                 # one command per missing run
    python -m benchmarks.ood_deletion --report               # OOD.md and one PNG per setup, like Fig. 3

Setups:

``pointmaze-medium``
    D4RL maze2d-style data made here: 100k steps of the waypoint controller
    with N(0, 0.5^2) action noise in ``PointMaze_Medium-v3``, goals redrawn on
    arrival (``recipes/collect_pointmaze.py``). Evaluation task
    ``pointmaze-medium-fixed``: start cell (1, 1), goal cell (6, 6). The
    regions are 0.8 m squares on 5 cells spread along the shortest path
    between them (the corridors are 1 m wide).
``antmaze-umaze``
    ``antmaze-umaze-v0-10k`` (shipped with the package) with POR's box
    x in [5, 10], y in [2, 7] (D4RL coordinates), evaluated in the D4RL
    antmaze-umaze task.
``antmaze-medium``
    ``antmaze-medium-diverse-v2-100k`` (the paper's Fig. 3 set; ``load_dataset``
    finds it in a data folder), evaluated in D4RL's medium test maze. The
    route from the start cell (1, 1) to the goal cell (6, 6) is unique; its
    five chokepoints, the route's cells with two open sides other than the
    start and goal, are (1, 2), (3, 3), (4, 5), (4, 6) and (5, 6) (D4RL's
    row, col), centred at (x, y) = (4, 0), (8, 8), (16, 12), (20, 12) and
    (20, 16). The regions are 2 m squares on them (the corridors are 4 m
    wide), so the route keeps its walls but loses its middle.

Results go to ``benchmarks/results/ood/<setup>/<method>/ratio<r>_seed<k>.json``
(temp file + rename; existing results are skipped unless ``--force``).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from benchmarks.baselines import MAZE_HYPERPARAMETERS, train_baseline
from benchmarks.harness import (machine_description, REPO, repo_relative, run_recipe, save_figure, skip_existing,
                                write_result)
from torchrl_tels.data import delete_regions, load_dataset, points_in_boxes
from torchrl_tels.envs import get_task, make_eval_env, rollout_episodes
from torchrl_tels.modules import load_tels_actor
from torchrl_tels.training import write_text
from torchrl_tels.run_folder import RunFolder

DEFAULT_RESULTS = REPO / "benchmarks" / "results" / "ood"
DEFAULT_WORK = REPO / "runs" / "ood"

METHODS = ("iql", "tels", "bc")
LABELS = {"iql": "IQL (TorchRL)", "tels": "TELS", "bc": "BC"}
RATIOS = (0.0, 0.7, 1.0)  # Fig. 3
ROLLOUTS = 20  # Fig. 3: 20 policy rollouts per panel
POINTMAZE_DATASET_ID = "local/pointmaze/medium-noisy-v0"
POINTMAZE_STEPS, POINTMAZE_NOISE = 100_000, 0.5  # D4RL maze2d's action noise


@dataclass(frozen=True)
class Setup:
    name: str
    dataset: str
    task: str
    maze_map: tuple[tuple[int, ...], ...]
    cell_size: float
    origin: tuple[float, float]  # (x, y) of the centre of cell (0, 0)
    start_cell: tuple[int, int]
    goal_cell: tuple[int, int]

    def cell_xy(self, cell) -> tuple[float, float]:
        return self.origin[0] + cell[1] * self.cell_size, self.origin[1] - cell[0] * self.cell_size


def _pointmaze_medium() -> tuple[Setup, list]:
    from torchrl_tels.collection import WaypointController
    from torchrl_tels.envs.pointmaze import FIXED_TASK_CELLS, make_pointmaze_env

    env = make_pointmaze_env("Medium")
    maze = env.unwrapped.maze
    start, goal = FIXED_TASK_CELLS["Medium"]
    setup = Setup("pointmaze-medium", POINTMAZE_DATASET_ID, "pointmaze-medium-fixed",
                  tuple(map(tuple, maze.maze_map)), 1.0, tuple(maze.cell_rowcol_to_xy(np.array([0, 0]))),
                  start, goal)
    inner = WaypointController(maze).shortest_path(start, goal)[1:-1]
    picks = np.round(np.linspace(0, len(inner) - 1, 5)).astype(int)
    boxes = []
    for i in picks:
        x, y = setup.cell_xy(inner[i])
        boxes.append((x - 0.4, x + 0.4, y - 0.4, y + 0.4))
    env.close()
    return setup, boxes


def _antmaze_umaze() -> tuple[Setup, list]:
    # D4RL's U-maze: 4 m cells, the start cell (3, 1) at the origin of D4RL's frame.
    u_maze = ((1, 1, 1, 1, 1), (1, 0, 0, 0, 1), (1, 1, 1, 0, 1), (1, 0, 0, 0, 1), (1, 1, 1, 1, 1))
    setup = Setup("antmaze-umaze", "antmaze-umaze-v0-10k", "antmaze-umaze-v0-10k", u_maze, 4.0, (-4.0, 12.0),
                  (3, 1), (1, 1))
    return setup, [(5.0, 10.0, 2.0, 7.0)]  # POR's box


def _antmaze_medium() -> tuple[Setup, list]:
    from torchrl_tels.envs.antmaze import MAZES

    maze = MAZES["medium"]
    rows = len(maze.rows)
    flipped = tuple(tuple(int(c == "1") for c in row) for row in reversed(maze.rows))  # Setup's rows grow down in y
    setup = Setup("antmaze-medium", "antmaze-medium-diverse-v2-100k", "antmaze-medium-diverse-v2-100k", flipped,
                  4.0, (-4.0, 4.0 * (rows - 2)), (rows - 2, 1), (rows - 1 - maze.goal_cell[0], maze.goal_cell[1]))
    chokepoints = ((1, 2), (3, 3), (4, 5), (4, 6), (5, 6))
    boxes = [(x - 1.0, x + 1.0, y - 1.0, y + 1.0) for x, y in (maze.cell_centre(c).tolist() for c in chokepoints)]
    return setup, boxes


SETUPS = {"pointmaze-medium": _pointmaze_medium, "antmaze-umaze": _antmaze_umaze, "antmaze-medium": _antmaze_medium}


def ensure_dataset(setup: Setup) -> None:
    """Makes the PointMaze data the first time (about 10 s); the AntMaze data ships with the package."""
    if setup.name != "pointmaze-medium":
        return
    import minari

    if setup.dataset in minari.list_local_datasets():
        return
    from torchrl_tels.collection import collect_pointmaze_dataset

    print(f"collecting {setup.dataset}: {POINTMAZE_STEPS} steps, action noise {POINTMAZE_NOISE}", flush=True)
    collect_pointmaze_dataset(setup.dataset, maze="Medium", n_steps=POINTMAZE_STEPS, seed=0,
                              action_noise=POINTMAZE_NOISE, author="torchrl_tels benchmarks/ood_deletion.py")


def result_path(results_dir: Path, setup: str, method: str, ratio: float, seed: int) -> Path:
    return results_dir / setup / method / f"ratio{ratio:g}_seed{seed}.json"


def one_command(args, setup: str, method: str, ratio: float, seed: int) -> list[str]:
    """The single-run command of (setup, method, ratio, seed) with this invocation's budget (run from the
    repository root)."""
    cmd = [sys.executable, "-m", "benchmarks.ood_deletion", f"--setup={setup}", f"--method={method}",
           f"--ratio={ratio:g}", f"--seed={seed}", f"--steps={args.steps}", f"--tsidm-steps={args.tsidm_steps}",
           f"--results-dir={args.results_dir}", f"--work-dir={args.work_dir}"]
    if args.threads:
        cmd.append(f"--threads={args.threads}")
    return cmd


def train_tels(setup: Setup, boxes, ratio: float, seed: int, args):
    run_dir = args.work_dir / setup.name / "tels" / f"ratio{ratio:g}_seed{seed}"
    box_list = "[" + ",".join("[" + ",".join(f"{v:g}" for v in box) + "]" for box in boxes) + "]"
    # One cheap final evaluation: the 20 rollouts below are the measurement.
    overrides = ["domain=maze", "budget=paper", f"dataset.name={setup.dataset}", f"dataset.task={setup.task}",
                 f"dataset.delete_boxes={box_list}", f"dataset.delete_ratio={ratio:g}", f"seed={seed}",
                 f"run_dir={run_dir}", "resume=true", "logger.wandb_mode=disabled",
                 f"tsidm.steps={args.tsidm_steps}", f"policy.steps={args.steps}", f"eval.interval={args.steps}",
                 "eval.episodes=1", "eval.last_n=1", f"checkpoint.interval={min(args.steps, 5000)}"]
    run_recipe(overrides, args.threads)
    env = make_eval_env(get_task(setup.task).env_id)
    folder = RunFolder(run_dir)
    actor = load_tels_actor(folder.policy_path, folder.tsidm_path, env.action_spec_unbatched)
    results = folder.read_results()
    return actor, env, {"run_dir": str(run_dir), "recipe_overrides": overrides,
                        "wall_time_s": results.get("wall_time_s"), "steps_per_s": results.get("steps_per_s")}


def train_baseline_policy(method: str, setup: Setup, data, seed: int, args):
    results, actor, env = train_baseline(
        method, data, task=setup.task, steps=args.steps, seed=seed, eval_interval=args.steps, eval_episodes=1,
        eval_last_n=1, eval_batched=False, threads=args.threads, hyperparameters=MAZE_HYPERPARAMETERS.get(method, {}),
        return_policy=True,
    )
    return actor, env, {"wall_time_s": results["wall_time_s"], "steps_per_s": results["steps_per_s"],
                        "hyperparameters": results["hyperparameters"]}


def run_one(setup_name: str, method: str, ratio: float, seed: int, args) -> Path:
    out = result_path(args.results_dir, setup_name, method, ratio, seed)
    if skip_existing(out, args.force):
        return out
    if args.threads:
        torch.set_num_threads(args.threads)
    started, start = datetime.now(timezone.utc), time.perf_counter()
    setup, boxes = SETUPS[setup_name]()
    ensure_dataset(setup)
    full = load_dataset(setup.dataset)
    data = delete_regions(full, boxes, ratio, seed=seed)  # the recipe deletes the same rows (same seed)
    inside = int(points_in_boxes(full, boxes).sum())
    print(f"== {setup_name} {method} ratio {ratio:g} seed {seed}: {len(full) - len(data)} of {inside} "
          f"transitions in the regions deleted, {len(data)} left", flush=True)

    torch.manual_seed(seed)
    if method == "tels":
        actor, env, extra = train_tels(setup, boxes, ratio, seed, args)
    else:
        actor, env, extra = train_baseline_policy(method, setup, data, seed, args)
    task = get_task(setup.task)
    paths, successes = [], []
    for rollout in rollout_episodes(actor, env, ROLLOUTS, seed=1_000_000 + seed * 1000,
                                    max_steps=task.max_episode_steps):
        xy = torch.cat([rollout["observation"][:, :2], rollout["next", "observation"][-1:, :2]])
        paths.append(np.round(xy.double().numpy(), 3).tolist())
        successes.append(bool(rollout["next", "reward"].sum() > 0))
    record = {
        "setup": setup_name, "method": method, "ratio": ratio, "seed": seed, "task": setup.task,
        "dataset": setup.dataset, "boxes": boxes, "transitions": len(full), "inside_regions": inside,
        "deleted": len(full) - len(data), "success_rate": sum(successes) / len(successes),
        "successes": successes, "paths": paths,
        "budget": {"policy_steps": args.steps, "tsidm_steps": args.tsidm_steps if method == "tels" else None,
                   "batch_size": 256, "rollouts": ROLLOUTS},
        "command": shlex.join(one_command(args, setup_name, method, ratio, seed)),
        "date": started.isoformat(timespec="seconds"), "elapsed_s": time.perf_counter() - start,
        "machine": machine_description(), "torch_threads": torch.get_num_threads(), **extra,
    }
    if write_result(out, record, args.force):
        print(f"== {setup_name} {method} ratio {ratio:g} seed {seed}: success {record['success_rate']:.2f} -> "
              f"{repo_relative(out)}", flush=True)
    return out


# ------------------------------------------------------------------ report
def load_results(results_dir: Path) -> dict:
    """{setup: {(method, ratio): [record, ...]}}."""
    found: dict = {}
    for path in sorted(results_dir.glob("*/*/ratio*_seed*.json")):
        record = json.loads(path.read_text())
        found.setdefault(record["setup"], {}).setdefault((record["method"], record["ratio"]), []).append(record)
    return found


def _draw_maze(ax, setup: Setup) -> None:
    from matplotlib.patches import Rectangle

    half = setup.cell_size / 2
    for i, row in enumerate(setup.maze_map):
        for j, cell in enumerate(row):
            if cell == 1:
                x, y = setup.cell_xy((i, j))
                ax.add_patch(Rectangle((x - half, y - half), setup.cell_size, setup.cell_size, color="0.35", lw=0))


def render_report(results_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    found = load_results(results_dir)
    lines = ["# OOD deletion test (TELS paper Fig. 3)", "",
             f"Generated {datetime.now(timezone.utc).isoformat(timespec='seconds')} by "
             "`python -m benchmarks.ood_deletion --report`. Success rate over "
             f"{ROLLOUTS} deterministic rollouts from the fixed start (mean over seeds; n = seeds). "
             "Every run of a setup has the same policy-step budget.", "",
             "| setup | method | budget | " + " | ".join(f"{r:.0%} deleted" for r in RATIOS) + " |",
             "|---|---|---|" + "---|" * len(RATIOS)]
    for setup_name, runs in sorted(found.items()):
        setup, boxes = SETUPS[setup_name]()
        methods = [m for m in METHODS if any(method == m for method, _ in runs)]  # those run on this setup
        for method in methods:
            cells, budgets = [], set()
            for ratio in RATIOS:
                records = runs.get((method, ratio), [])
                budgets |= {(r["budget"]["policy_steps"], r["budget"]["tsidm_steps"]) for r in records}
                if records:
                    rates = [r["success_rate"] for r in records]
                    cells.append(f"{100 * statistics.fmean(rates):.0f} % (n={len(rates)}; deleted "
                                 f"{records[0]['deleted']}/{records[0]['inside_regions']})")
                else:
                    cells.append("—")
            budget = "; ".join(f"{p // 1000}k policy steps" + (f", TS-IDM {t // 1000}k steps" if t else "")
                               for p, t in sorted(budgets))
            lines.append(f"| {setup_name} | {LABELS[method]} | {budget} | " + " | ".join(cells) + " |")

        full = load_dataset(setup.dataset)
        fig, axes = plt.subplots(len(methods), len(RATIOS), figsize=(3.2 * len(RATIOS), 3.2 * len(methods)),
                                 squeeze=False)
        for col, ratio in enumerate(RATIOS):
            kept = delete_regions(full, boxes, ratio, seed=0)["observation"][:, :2].numpy()
            step = max(1, len(kept) // 6000)
            for row, method in enumerate(methods):
                ax = axes[row][col]
                _draw_maze(ax, setup)
                ax.scatter(kept[::step, 0], kept[::step, 1], s=0.3, color="tab:blue", alpha=0.25, lw=0)
                for xmin, xmax, ymin, ymax in boxes:
                    ax.add_patch(Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, color="red", alpha=0.25, lw=0))
                records = runs.get((method, ratio), [])
                if records:
                    record = records[0]  # one seed per panel, as the paper's figure
                    for path, success in zip(record["paths"], record["successes"]):
                        path = np.asarray(path)
                        ax.plot(path[:, 0], path[:, 1], lw=0.8, color="tab:green" if success else "tab:orange")
                    title = f"{LABELS[method]}, {ratio:.0%} deleted: {record['success_rate']:.0%} success"
                else:
                    title = f"{LABELS[method]}, {ratio:.0%} deleted: not run"
                sx, sy = setup.cell_xy(setup.start_cell)
                gx, gy = setup.cell_xy(setup.goal_cell)
                ax.scatter([sx], [sy], marker="x", s=60, color="red", zorder=4)
                ax.scatter([gx], [gy], marker="*", s=120, color="gold", edgecolor="k", zorder=4)
                ax.set_title(title, fontsize=8)
                ax.set_aspect("equal")
                ax.set_xticks([]), ax.set_yticks([])
        fig.suptitle(f"{setup_name}: data (blue), deleted regions (red), {ROLLOUTS} rollouts "
                     "(green: reached the goal)", fontsize=9)
        fig.tight_layout()
        save_figure(fig, results_dir / "plots" / f"{setup_name}.png")
        plt.close(fig)
    lines += [""] + [f"![{name}](plots/{name}.png)" for name in sorted(found)] + [
        "", "Each result JSON holds its command, date, machine, thread count, budget, the deleted counts "
        "and every rollout's (x, y) path.", ""]
    table = results_dir / "OOD.md"
    table.parent.mkdir(parents=True, exist_ok=True)
    write_text(table, "\n".join(lines))
    return table


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.split("\n\n")[0])
    parser.add_argument("--setup", "--setups", action="extend", nargs="+", choices=sorted(SETUPS))
    parser.add_argument("--method", "--methods", action="extend", nargs="+", choices=METHODS)
    parser.add_argument("--ratio", "--ratios", action="extend", nargs="+", type=float)
    parser.add_argument("--seed", "--seeds", action="extend", nargs="+", type=int)
    parser.add_argument("--steps", type=int, default=5000, help="policy steps for every method (paper: 100k)")
    parser.add_argument("--tsidm-steps", "--tsidm_steps", type=int, default=3000, help="TELS stage-1 steps")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads per run")
    parser.add_argument("--results-dir", "--results_dir", type=Path, default=DEFAULT_RESULTS)
    parser.add_argument("--work-dir", "--work_dir", type=Path, default=DEFAULT_WORK)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--grid", action="store_true", help="every missing combination, one after another")
    parser.add_argument("--list", action="store_true", help="print one command per missing run")
    parser.add_argument("--report", action="store_true", help="write OOD.md and the PNGs from the results")
    args = parser.parse_args(argv)
    for ratio in args.ratio or ():
        if not 0.0 <= ratio <= 1.0:
            parser.error(f"--ratio must lie in [0, 1], got {ratio}")
    if args.steps < 1 or args.tsidm_steps < 1:
        parser.error("--steps and --tsidm-steps must be positive")
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    # The PointMaze data lives with the other run outputs, not in the user's ~/.minari.
    os.environ.setdefault("MINARI_DATASETS_PATH", str((args.work_dir / "minari").resolve()))
    if args.report:
        print(render_report(args.results_dir))
        return
    combos = [(s, m, r, k) for s in (args.setup or SETUPS) for r in (args.ratio or RATIOS)
              for k in (args.seed or (0,)) for m in (args.method or METHODS)]
    if args.list:
        for combo in combos:
            if not result_path(args.results_dir, combo[0], combo[1], combo[2], combo[3]).exists():
                print(shlex.join(one_command(args, *combo)))
        return
    if not args.grid and len(combos) != 1:
        raise SystemExit("give one --setup, --method, --ratio and --seed (or --grid / --list / --report)")
    for combo in combos:
        run_one(*combo, args)


if __name__ == "__main__":
    main()
