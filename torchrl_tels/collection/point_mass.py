"""A poor behaviour policy's data for the point-mass task (:mod:`torchrl_tels.envs.point_mass`)."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from torchrl_tels.envs.point_mass import EPISODE_STEPS, PointMassGoal

__all__ = ["make_point_mass_dataset"]


def make_point_mass_dataset(
    path: str | os.PathLike,
    n_transitions: int = 5000,
    seed: int = 0,
    *,
    heading_strength: float = 0.5,
) -> float:
    """Write a D4RL-style ``.npz`` from a poor behaviour policy; return its best episode return.

    The behaviour policy knows nothing of the goal. Each episode draws a
    heading :math:`u` uniformly on the unit circle and then acts
    ``heading_strength * u + noise`` at every step, with ``noise`` uniform in
    ``[-1, 1]^2``, clipped to the action box: a noisy straight walk in a random
    direction. The data covers a disc around the start that contains the goal,
    and the whole action box (so an inverse dynamics model can be learned),
    but

    * only the few episodes (3 to 10 in 100) whose heading points at the goal
      and whose noise does not push them aside reach it, slowly: with 5000
      transitions the best episode scores between about -13 and -18 (seeds
      0-7), against -6.36 for the optimum, and most episodes score below -50;
    * the behaviour's mean action carries no information about the goal, so
      imitating it goes nowhere useful (about -70 for standing still).

    Doing clearly better than the best episode needs what offline RL adds: a
    value function that tells which observed next states lead to the goal,
    and a policy that takes the best of them in every state, stitching the
    fast moves of many different episodes.

    Episodes end in ``terminals`` where they reach the goal and in ``timeouts``
    after :data:`EPISODE_STEPS` steps; the last one is cut short (a timeout)
    where ``n_transitions`` runs out.

    Args:
        path: where to write the ``.npz`` (keys ``observations``, ``actions``,
            ``rewards``, ``next_observations``, ``terminals``, ``timeouts``).
        n_transitions: number of transitions, at least one episode.
        seed: seed of the behaviour policy.

    Keyword Args:
        heading_strength: how strongly an episode follows its heading.

    Returns:
        The highest undiscounted return among the complete episodes (those
        that reached the goal or the time limit).
    """
    if n_transitions < EPISODE_STEPS:
        raise ValueError(f"n_transitions must be at least one episode ({EPISODE_STEPS}), got {n_transitions}.")
    rng = np.random.default_rng(seed)
    env = PointMassGoal()
    columns = {key: [] for key in ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")}
    returns = []
    while len(columns["rewards"]) < n_transitions:
        obs, _ = env.reset()
        angle = rng.uniform(0.0, 2 * math.pi)
        heading = heading_strength * np.array([math.cos(angle), math.sin(angle)])
        episode_return = 0.0
        for t in range(EPISODE_STEPS):
            action = np.clip(heading + rng.uniform(-1.0, 1.0, size=2), -1.0, 1.0).astype(np.float32)
            next_obs, reward, terminated, _, _ = env.step(action)
            episode_return += reward
            complete = terminated or t == EPISODE_STEPS - 1
            timeout = not terminated and (complete or len(columns["rewards"]) + 1 == n_transitions)
            for key, value in (("observations", obs), ("actions", action), ("rewards", reward),
                               ("next_observations", next_obs), ("terminals", terminated), ("timeouts", timeout)):
                columns[key].append(value)
            obs = next_obs
            if terminated or timeout:
                break
        if complete:
            returns.append(episode_return)
    arrays = {
        key: np.asarray(values, dtype=bool if key in ("terminals", "timeouts") else np.float32)
        for key, values in columns.items()
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as file:  # np.savez would append ".npz" to another suffix
        np.savez(file, **arrays)
    return float(max(returns)) if returns else -math.inf
