"""Generate a D4RL maze2d-style PointMaze dataset (waypoint controller) as a Minari dataset.

Examples::

    # 100k steps in the U-maze, noiseless controller
    python recipes/collect_pointmaze.py --maze UMaze --steps 100000

    # D4RL-like noisy data in the medium maze, under a chosen id
    python recipes/collect_pointmaze.py --maze Medium --steps 100000 --noise 0.5 \\
        --dataset-id local/pointmaze/medium-noisy-v0

The dataset is written under ``MINARI_DATASETS_PATH`` (default
``~/.minari/datasets``) and read back with
``torchrl_tels.data.load_dataset("<dataset id>")``: 8-dim observations
``[x, y, goal_x, goal_y, x, y, vx, vy]``, 2-dim actions, sparse reward 1 on
reaching the goal (which ends an episode unless ``--continuous``).
Evaluate a policy trained on it with the task ``pointmaze-<maze>`` (e.g.
``dataset.task=pointmaze-umaze``), whose environment is the episodic maze
with the same flat observation. Needs the ``maze`` extra
(``pip install "torchrl-tels[maze]"``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

from torchrl_tels.collection import collect_pointmaze_dataset
from torchrl_tels.envs.pointmaze import MAZE_ENV_IDS, pointmaze_task_name


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--maze", choices=sorted(MAZE_ENV_IDS), default="UMaze", help="Maze layout."
    )
    parser.add_argument(
        "--steps", type=int, default=100_000, help="Number of transitions (default 100000)."
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="Std of Gaussian action noise (D4RL's maze2d used 0.5; default 0).",
    )
    parser.add_argument(
        "--dataset-id",
        default=None,
        help="Minari id to write (default: local/pointmaze/<maze>-v0).",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--continuous",
        action="store_true",
        help="Store one continuous episode instead of one episode per goal reached.",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="Replace an existing dataset."
    )
    parser.add_argument("--author", default=None)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    dataset_id = args.dataset_id or f"local/pointmaze/{args.maze.lower()}-v0"
    metadata = {"author": args.author} if args.author is not None else {}
    start = time.perf_counter()
    try:
        dataset = collect_pointmaze_dataset(
            dataset_id,
            maze=args.maze,
            n_steps=args.steps,
            seed=args.seed,
            action_noise=args.noise,
            split_at_goals=not args.continuous,
            overwrite=args.overwrite,
            **metadata,
        )
    except (ImportError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    print(
        f"Wrote {dataset_id}: {dataset.total_episodes} episodes, "
        f"{dataset.total_steps} steps in {time.perf_counter() - start:.1f} s, at "
        f"{dataset.spec.data_path}. Evaluation task: {pointmaze_task_name(args.maze)}."
    )


if __name__ == "__main__":
    main()
