"""Record a Minari dataset from a Gymnasium environment.

Examples::

    # 10 episodes of uniform random actions in Hopper-v4
    python recipes/collect_dataset.py --env Hopper-v4 \\
        --dataset-id local/hopper/random-v0 --episodes 10

    # 5000 steps of a policy defined in your own module, with action noise
    python recipes/collect_dataset.py --env Hopper-v4 \\
        --dataset-id local/hopper/mine-v0 --steps 5000 \\
        --policy my_package.policies:expert --action-noise 0.1

The dataset is written under ``MINARI_DATASETS_PATH`` (default
``~/.minari/datasets``) and can then be read with
``torchrl_tels.data.load_dataset("local/hopper/random-v0")``.

``--policy`` is ``random`` or ``module:attribute`` naming a callable that maps
one observation to one action (or a TorchRL actor reading ``"observation"``
and writing ``"action"``); no pickled object is ever loaded.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Sequence

from torchrl_tels.collection import collect_minari_dataset


def load_policy(spec: str):
    """Return ``None`` for ``"random"``, else the object named ``module:attribute``."""
    if spec == "random":
        return None
    module_name, sep, attribute = spec.partition(":")
    if not sep or not module_name or not attribute:
        raise SystemExit(
            f"--policy must be 'random' or 'module:attribute', got {spec!r}."
        )
    policy = importlib.import_module(module_name)
    for part in attribute.split("."):
        policy = getattr(policy, part)
    if not callable(policy):
        raise SystemExit(f"--policy {spec!r} is not callable.")
    return policy


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True, help="Gymnasium environment id.")
    parser.add_argument(
        "--dataset-id",
        required=True,
        help="Minari id to write, e.g. local/hopper/random-v0.",
    )
    amount = parser.add_mutually_exclusive_group(required=True)
    amount.add_argument("--episodes", type=int, help="Number of whole episodes.")
    amount.add_argument("--steps", type=int, help="Number of environment steps.")
    parser.add_argument(
        "--policy",
        default="random",
        help="'random' or module:attribute (default: random).",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--action-noise", type=float, default=0.0, help="Std of Gaussian action noise."
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="Replace an existing dataset."
    )
    parser.add_argument("--author", default=None)
    parser.add_argument("--description", default=None)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    metadata = {
        key: value
        for key, value in (("author", args.author), ("description", args.description))
        if value is not None
    }
    dataset = collect_minari_dataset(
        args.env,
        args.dataset_id,
        policy=load_policy(args.policy),
        n_episodes=args.episodes,
        n_steps=args.steps,
        seed=args.seed,
        action_noise=args.action_noise,
        overwrite=args.overwrite,
        **metadata,
    )
    print(
        f"Wrote {args.dataset_id}: {dataset.total_episodes} episodes, "
        f"{dataset.total_steps} steps, at {dataset.storage.data_path}"
    )


if __name__ == "__main__":
    main()
