"""Make one of D4RL's AntMaze medium/large sets as D4RL made it (100 episodes × 1001 transitions).

    python recipes/collect_antmaze.py medium-diverse            # -> ~/.cache/torchrl_tels/datasets/
    python recipes/collect_antmaze.py large-play --seed 3 --out data/

The file is ``<out>/antmaze-<set>-v2-100k.npz`` (D4RL's keys, see ``torchrl_tels.collection.antmaze``);
``torchrl_tels.data.load_dataset("antmaze-<set>-v2-100k")`` and the recipe find it in the default folder
(``$TORCHRL_TELS_DATA`` moves it). New samples of D4RL's process, seeded: not D4RL's released files.
Needs the ``robotics`` extra.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from torchrl_tels.collection.antmaze import ANTMAZE_SETS, collect_antmaze
from torchrl_tels.data import user_datasets_dir
from torchrl_tels.errors import TelsError


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("set", choices=sorted(ANTMAZE_SETS), help="which D4RL AntMaze set")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=100, help="episodes of 1001 transitions (default 100)")
    parser.add_argument("--out", type=Path, default=None, help="folder (default: $TORCHRL_TELS_DATA or "
                                                                  "~/.cache/torchrl_tels/datasets)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    out = (args.out or user_datasets_dir()).expanduser()
    arrays = collect_antmaze(args.set, episodes=args.episodes, seed=args.seed)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"antmaze-{args.set}-v2-100k.npz"
    # written whole or not at all: a temporary file in the same folder, renamed
    fd, tmp = tempfile.mkstemp(dir=out, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as file:
            np.savez_compressed(file, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    reached = int(arrays["rewards"].sum())
    print(f"wrote {path}: {len(arrays['actions'])} transitions, {reached} within 0.5 of the evaluation goal "
          f"{np.round(arrays['eval_goal'], 3).tolist()}")
    return path


if __name__ == "__main__":
    try:
        main()
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
