"""Is a zero on AntMaze medium/large a bug or the task? Where the data goes, where a policy goes, and whether the
goal is reachable at all in the evaluation environment.

For one 100k set, three readings, written to ``benchmarks/results/antmaze100k/reach/<task>.json``:

* **data**: how many episodes were commanded to the evaluation goal's cell, and how many came within 0.5 of
  the relabel goal (a goal-agnostic imitation of the data mostly goes elsewhere);
* **navigator**: D4RL's own goal-reaching policy and waypoint controller, started as the evaluation starts,
  driven to each evaluation goal: the rate at which the goal is reachable in 1000 steps in this environment;
* **policy**: a baseline trained on the set (``--method``, ``--steps``), rolled out deterministically from the
  evaluation start: its success rate, its closest approach to the goal in maze cells along the corridors (breadth-first steps from the goal cell), and how long it stays upright (torso z > 0.3).

Run from the repository root::

    python -m benchmarks.antmaze_reach --task antmaze-medium-diverse-v2-100k --method bc --steps 20000 --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from datetime import datetime, timezone

import gymnasium as gym
import numpy as np
import torch

from benchmarks.baselines import MAZE_HYPERPARAMETERS, train_baseline
from benchmarks.harness import code_version, invocation, machine_description, REPO, write_result
from torchrl_tels.collection.antmaze import ACTION_NOISE, GoalReachingAnt, next_waypoint
from torchrl_tels.envs import antmaze, get_task, rollout_episodes

RESULTS = REPO / "benchmarks" / "results" / "antmaze100k" / "reach"
UPRIGHT_Z = 0.3  # a flipped ant rests at z ≈ 0.26


def data_reading(task: str) -> dict:
    from torchrl_tels.data import load_dataset

    maze = antmaze.maze_of_task(task)
    data = load_dataset(task)
    xy = data["observation"][:, :2].double().numpy()
    in_goal_cell = np.array([maze.cell_at(p) == maze.goal_cell for p in xy])
    return {"transitions": len(data), "rewarded_transitions": int((data["next", "reward"] > 0).sum()),
            "goal_cell": list(maze.goal_cell), "goal_cell_share": float(in_goal_cell.mean())}


def navigator_reading(task: str, episodes: int, seed: int) -> dict:
    maze = antmaze.maze_of_task(task)
    env = gym.make(get_task(task).env_id)
    policy, rng = GoalReachingAnt(), np.random.default_rng(seed)
    reached, lengths = [], []
    for episode in range(episodes):
        observation, info = env.reset(seed=seed + episode)
        goal, done, success, steps = info["goal"], False, False, 0
        while not done:
            waypoint = next_waypoint(maze, observation[:2], goal, rng)
            action = np.clip(policy(observation, waypoint - observation[:2], rng)
                             + ACTION_NOISE * rng.standard_normal(8), -1, 1)
            observation, _, success, truncated, _ = env.step(action)
            done, steps = success or truncated, steps + 1
        reached.append(bool(success)), lengths.append(steps)
    env.close()
    return {"episodes": episodes, "success_rate": statistics.fmean(reached),
            "median_steps_when_reached": statistics.median([n for n, r in zip(lengths, reached) if r] or [0])}


def policy_reading(task: str, method: str, steps: int, episodes: int, seed: int, threads: int | None) -> dict:
    maze = antmaze.maze_of_task(task)
    distance = maze.distances_to(maze.goal_cell)
    results, actor, env = train_baseline(method, task, steps=steps, seed=seed, eval_interval=steps, eval_episodes=1,
                                         eval_last_n=1, eval_batched=False, threads=threads,
                                         hyperparameters=MAZE_HYPERPARAMETERS.get(method, {}), return_policy=True)
    per_episode = []
    for rollout in rollout_episodes(actor, env, episodes, seed=2_000_000 + seed * 1000,
                                    max_steps=get_task(task).max_episode_steps):
        observations = rollout["next", "observation"].double().numpy()
        xy = observations[:, :2]
        # the cell each point lies in (D4RL's cell_of is shifted half a cell, for steering, not for this)
        cells = [distance.get(maze.cell_at(p)) for p in xy]
        per_episode.append({
            "success": bool(rollout["next", "reward"].sum() > 0),
            "closest_cells": min((c for c in cells if c is not None), default=None),
            "upright_share": float((observations[:, 2] > UPRIGHT_Z).mean()),
            "final_xy": xy[-1].round(2).tolist(),
        })
    env.close()
    start_cells = distance[(1, 1)]  # the evaluation starts at the origin, the centre of cell (1, 1)
    return {"method": method, "steps": steps, "episodes": episodes,
            "success_rate": statistics.fmean(e["success"] for e in per_episode),
            "start_cells_from_goal": start_cells,
            "median_closest_cells": statistics.median(e["closest_cells"] for e in per_episode
                                                      if e["closest_cells"] is not None),
            "median_upright_share": statistics.median(e["upright_share"] for e in per_episode),
            "per_episode": per_episode, "train": {k: results[k] for k in ("wall_time_s", "steps_per_s")}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.antmaze_reach", description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True, choices=sorted(n + "-100k" for n in antmaze.TASK_NAMES
                                                                if "umaze" not in n))
    parser.add_argument("--method", default="bc", choices=("bc", "iql", "td3bc"))
    parser.add_argument("--steps", type=int, default=20_000, help="the baseline's policy steps")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    started, start = datetime.now(timezone.utc), time.perf_counter()
    torch.manual_seed(args.seed)
    record = {"task": args.task, "seed": args.seed, "data": data_reading(args.task),
              "navigator": navigator_reading(args.task, args.episodes, args.seed),
              "policy": policy_reading(args.task, args.method, args.steps, args.episodes, args.seed, args.threads),
              "command": invocation(), "date": started.isoformat(timespec="seconds"),
              "elapsed_s": time.perf_counter() - start, "machine": machine_description(), "code": code_version(),
              "torch_threads": torch.get_num_threads()}
    out = RESULTS / f"{args.task}_{args.method}_seed{args.seed}.json"
    write_result(out, record, args.force)
    p, n = record["policy"], record["navigator"]
    print(f"{args.task}: navigator {n['success_rate']:.2f}; {args.method} success {p['success_rate']:.2f}, closest "
          f"{p['median_closest_cells']} cells from the goal (start {p['start_cells_from_goal']}), upright "
          f"{p['median_upright_share']:.2f} -> {out.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
