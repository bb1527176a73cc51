"""A tiny deterministic 2-D point-mass task for learning tests and demos.

The agent is a point in the plane that starts at the origin and must reach
the goal :math:`g = (1, 1)`. Each step it moves by ``0.1 * a`` for an action
:math:`a \\in [-1, 1]^2` and receives minus its distance to the goal:

.. math::

    s_{t+1} = s_t + 0.1\\, a_t, \\qquad r_t = -\\|s_{t+1} - g\\|_2 ,

and the episode terminates once :math:`\\|s_{t+1} - g\\|_2 <` :data:`GOAL_RADIUS`
(0.2), or is truncated after :data:`EPISODE_STEPS` (50) steps. The return
measures how fast the goal is reached: the straight diagonal run (9 steps) scores
:data:`OPTIMAL_RETURN` (about -6.36), standing still about -70.7 and a
uniformly random policy :data:`RANDOM_RETURN` (about -72.3).

Importing this module registers the environment with Gymnasium as
:data:`ENV_ID` and the evaluation task :data:`TASK_NAME` with
:func:`~torchrl_tels.envs.register_task` (both idempotent), so that::

    python recipes/tels_offline.py dataset.name=<file.npz> dataset.task=pointmass-goal

works (``torchrl_tels.envs``, which the recipe imports, imports this module).
:func:`torchrl_tels.collection.make_point_mass_dataset` writes a
D4RL-style ``.npz`` of a poor behaviour policy for that task.
"""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torchrl_tels.envs.tasks import get_task, register_task, Task

__all__ = [
    "ENV_ID",
    "EPISODE_STEPS",
    "GOAL",
    "GOAL_RADIUS",
    "OPTIMAL_RETURN",
    "RANDOM_RETURN",
    "START",
    "TASK_NAME",
    "PointMassGoal",
    "register_point_mass_env",
    "register_point_mass_task",
]

#: Gymnasium id of :class:`PointMassGoal`.
ENV_ID = "torchrl_tels/PointMassGoal-v0"
#: Name of the evaluation task registered with :func:`~torchrl_tels.envs.register_task`.
TASK_NAME = "pointmass-goal"
#: Episode length (Gymnasium ``TimeLimit``).
EPISODE_STEPS = 50
START = (0.0, 0.0)
GOAL = (1.0, 1.0)
#: The episode terminates when the point comes closer than this to the goal.
GOAL_RADIUS = 0.2
#: Largest move per step along each axis (an action of ±1).
MAX_STEP = 0.1
#: Positions are clipped to ``[-BOUND, BOUND]^2``, far outside anything the task visits.
BOUND = 5.0

#: Return of the optimal policy, full speed along the diagonal (9 steps): about -6.36.
OPTIMAL_RETURN = -math.sqrt(2.0) * sum(k / 10 for k in range(1, 10))
#: Mean return of the uniformly random policy (2000 episodes): about -72.3.
RANDOM_RETURN = -72.34


class PointMassGoal(gym.Env):
    """Deterministic 2-D point mass that must reach a fixed goal.

    Observation: the position ``(x, y)`` (float32). Action: a velocity command
    in ``[-1, 1]^2`` (clipped), scaled by :data:`MAX_STEP`. Reward: minus the
    Euclidean distance from the new position to :data:`GOAL`. The episode
    terminates when that distance drops below :data:`GOAL_RADIUS`; the time
    limit comes from the registration (``gym.make(ENV_ID)`` truncates after
    :data:`EPISODE_STEPS` steps). Reset always starts at :data:`START`: the task
    is fully deterministic, whatever the seed.
    """

    metadata = {"render_modes": []}

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Box(-BOUND, BOUND, shape=(2,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._goal = np.asarray(GOAL, dtype=np.float64)
        self._position = np.asarray(START, dtype=np.float64)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._position = np.asarray(START, dtype=np.float64)
        return self._position.astype(np.float32), {}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -1.0, 1.0)
        self._position = np.clip(self._position + MAX_STEP * action, -BOUND, BOUND)
        distance = float(np.linalg.norm(self._position - self._goal))
        return self._position.astype(np.float32), -distance, distance < GOAL_RADIUS, False, {"distance": distance}


def register_point_mass_env() -> None:
    """Register :class:`PointMassGoal` with Gymnasium as :data:`ENV_ID` (no-op if done)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point=f"{__name__}:PointMassGoal", max_episode_steps=EPISODE_STEPS)


def register_point_mass_task() -> Task:
    """Register (once) and return the evaluation task :data:`TASK_NAME`.

    Its reference returns are the random policy's (normalized score 0) and the
    optimal policy's (normalized score 100).
    """
    register_point_mass_env()
    try:
        return get_task(TASK_NAME)
    except ValueError:
        pass
    return register_task(
        Task(TASK_NAME, ENV_ID, RANDOM_RETURN, OPTIMAL_RETURN, 2, 2, max_episode_steps=EPISODE_STEPS)
    )


register_point_mass_env()
register_point_mass_task()
