"""PointMaze evaluation environments and tasks (Gymnasium-Robotics ``PointMaze_*-v3``).

* :func:`make_pointmaze_env` / :data:`EVAL_ENV_IDS`: the episodic evaluation
  task with the dict observation flattened the way ``load_dataset`` flattens
  the dataset's, so a policy trained on the data can act in it directly.
* :data:`FIXED_EVAL_ENV_IDS`: the same with one start and one goal cell.

**Observation layout.** PointMaze observations are dicts; ``load_dataset``
concatenates their entries in the observation space's (sorted) key order, so
a dataset row's ``"observation"`` is 8 numbers::

    [0:2] achieved_goal (x, y)   [2:4] desired_goal   [4:8] observation (x, y, vx, vy)

``(x, y)`` sits in columns 0-1, where :func:`~torchrl_tels.data.delete_regions`
looks by default. Positions are in Gymnasium-Robotics coordinates: 1 m cells,
maze centred on the origin, rows growing towards -y.

Importing this module registers, needing Gymnasium only, the evaluation
environments and the tasks ``pointmaze-umaze``, ``pointmaze-medium`` and
``pointmaze-large`` (reference scores 0 and 1, so the normalized score is the
success rate times 100), and their ``-fixed`` variants. Gymnasium-Robotics
(the ``maze`` extra) is imported only when an environment is built. The data
collection lives in :mod:`torchrl_tels.collection.pointmaze`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from torchrl_tels.envs.robotics import import_gymnasium_robotics, maze_files_removed
from torchrl_tels.envs.tasks import register_task, Task

__all__ = [
    "EVAL_ENV_IDS",
    "FIXED_EVAL_ENV_IDS",
    "FIXED_TASK_CELLS",
    "MAZE_ENV_IDS",
    "MAZE_MAX_EPISODE_STEPS",
    "POINTMAZE_OBSERVATION_KEYS",
    "check_maze",
    "make_pointmaze_env",
    "pointmaze_task_name",
    "register_pointmaze_envs",
    "register_pointmaze_tasks",
]

#: Gymnasium-Robotics environment of each maze.
MAZE_ENV_IDS: dict[str, str] = {
    "UMaze": "PointMaze_UMaze-v3",
    "Medium": "PointMaze_Medium-v3",
    "Large": "PointMaze_Large-v3",
}
#: Evaluation episode limits (D4RL maze2d's, also Gymnasium-Robotics' defaults).
MAZE_MAX_EPISODE_STEPS: dict[str, int] = {"UMaze": 300, "Medium": 600, "Large": 800}
#: Episodic evaluation environments with flat 8-dim observations.
EVAL_ENV_IDS: dict[str, str] = {
    maze: f"torchrl_tels/PointMaze{maze}Flat-v0" for maze in MAZE_ENV_IDS
}
#: Start and goal cells (row, col) of the fixed-task evaluation envs: opposite
#: corners joined by the longest corridor, like D4RL antmaze's start and goal.
FIXED_TASK_CELLS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "UMaze": ((3, 1), (1, 1)),
    "Medium": ((1, 1), (6, 6)),
    "Large": ((1, 1), (7, 10)),
}
#: Episodic evaluation environments with a fixed start and goal cell
#: (:data:`FIXED_TASK_CELLS`), flat 8-dim observations.
FIXED_EVAL_ENV_IDS: dict[str, str] = {
    maze: f"torchrl_tels/PointMaze{maze}FixedFlat-v0" for maze in MAZE_ENV_IDS
}
#: Dict entries in the order ``load_dataset`` concatenates them by default.
POINTMAZE_OBSERVATION_KEYS: tuple[str, ...] = ("achieved_goal", "desired_goal", "observation")


def check_maze(maze: str) -> str:
    if maze not in MAZE_ENV_IDS:
        raise ValueError(f"Unknown maze {maze!r}; expected one of {list(MAZE_ENV_IDS)}.")
    return maze



# --------------------------------------------------------------------------- #
# Environments and tasks
# --------------------------------------------------------------------------- #
def make_pointmaze_env(
    maze: str = "UMaze", *, flatten: bool = False, **kwargs: Any
) -> gym.Env:
    """Build ``PointMaze_<maze>-v3`` (Gymnasium-Robotics imported here).

    Args:
        maze: ``"UMaze"``, ``"Medium"`` or ``"Large"``.

    Keyword Args:
        flatten: wrap it in :class:`gymnasium.wrappers.FlattenObservation`,
            which gives the 8-dim vector of the module docstring (the same
            layout as a dataset row).
        **kwargs: forwarded to :func:`gymnasium.make` (``continuing_task``,
            ``reset_target``, ``reward_type``, ``max_episode_steps``, ...).

    Raises:
        ImportError: Gymnasium-Robotics is not installed.
    """
    import_gymnasium_robotics()
    with maze_files_removed():
        env = gym.make(MAZE_ENV_IDS[check_maze(maze)], **kwargs)
    if flatten:
        keys = tuple(env.observation_space.spaces)
        if keys != POINTMAZE_OBSERVATION_KEYS:  # pragma: no cover - gymnasium sorts
            raise RuntimeError(f"unexpected PointMaze observation keys {keys}.")
        env = gym.wrappers.FlattenObservation(env)
    return env


def _make_flat_eval_env(maze: str, **kwargs: Any) -> gym.Env:
    kwargs.setdefault("continuing_task", False)
    # The registered id adds the step limit: start from the bare environment.
    import_gymnasium_robotics()
    with maze_files_removed():
        env = gym.make(MAZE_ENV_IDS[check_maze(maze)], **kwargs).unwrapped
    return gym.wrappers.FlattenObservation(env)


def _make_fixed_eval_env(maze: str, **kwargs: Any) -> gym.Env:
    # Gymnasium-Robotics draws the reset position in the "r" cell and the goal
    # in the "g" cell (each with its usual +-0.25 cell jitter).
    import_gymnasium_robotics()
    from gymnasium_robotics.envs.maze.maps import GOAL, RESET

    start, goal = FIXED_TASK_CELLS[check_maze(maze)]
    maze_map = [list(row) for row in _maze_map(maze)]
    maze_map[start[0]][start[1]] = RESET
    maze_map[goal[0]][goal[1]] = GOAL
    return _make_flat_eval_env(maze, maze_map=maze_map, **kwargs)


def _maze_map(maze: str) -> list[list[Any]]:
    from gymnasium_robotics.envs.maze import maps

    return {"UMaze": maps.U_MAZE, "Medium": maps.MEDIUM_MAZE, "Large": maps.LARGE_MAZE}[check_maze(maze)]


def register_pointmaze_envs() -> None:
    """Register :data:`EVAL_ENV_IDS` and :data:`FIXED_EVAL_ENV_IDS` with Gymnasium (no-op if done).

    Each is the episodic task (``continuing_task=False``: the episode ends,
    with reward 1, when the point is within 0.45 of the goal) with a flat
    observation, truncated at :data:`MAZE_MAX_EPISODE_STEPS`. The first set
    draws start and goal cells at random; the second always starts in the
    same cell and has the same goal cell (:data:`FIXED_TASK_CELLS`).
    """
    for ids, entry_point in ((EVAL_ENV_IDS, "_make_flat_eval_env"), (FIXED_EVAL_ENV_IDS, "_make_fixed_eval_env")):
        for maze, env_id in ids.items():
            if env_id not in gym.registry:
                gym.register(
                    id=env_id,
                    entry_point=f"{__name__}:{entry_point}",
                    kwargs={"maze": maze},
                    max_episode_steps=MAZE_MAX_EPISODE_STEPS[maze],
                )


def pointmaze_task_name(maze: str, fixed: bool = False) -> str:
    """Task name of a maze: ``"pointmaze-umaze"``, ``"pointmaze-medium"``, ...; ``"pointmaze-medium-fixed"``."""
    return f"pointmaze-{check_maze(maze).lower()}" + ("-fixed" if fixed else "")


def register_pointmaze_tasks(
    *dataset_names: str, maze: str | None = None, fixed: bool = False
) -> list[Task]:
    """Register evaluation tasks on :data:`EVAL_ENV_IDS` (replacing old ones).

    Without arguments, registers ``pointmaze-<maze>`` for the three mazes
    (done on import, as is ``fixed=True``). With dataset names (e.g. a Minari
    id written by :func:`collect_pointmaze_dataset`) and ``maze``, registers
    those names for that maze, so ``get_task(<dataset id>)`` finds the task.
    ``fixed=True`` evaluates on :data:`FIXED_EVAL_ENV_IDS` instead (one start
    and one goal cell) and names the default tasks ``pointmaze-<maze>-fixed``.
    """
    if dataset_names and maze is None:
        raise ValueError("register_pointmaze_tasks: give maze= with dataset names.")
    mazes = [check_maze(maze)] if maze is not None else list(MAZE_ENV_IDS)
    env_ids = FIXED_EVAL_ENV_IDS if fixed else EVAL_ENV_IDS
    tasks = []
    for name_maze in mazes:
        names = dataset_names or (pointmaze_task_name(name_maze, fixed),)
        for name in names:
            task = Task(
                name,
                env_ids[name_maze],
                0.0,
                1.0,
                observation_dim=8,
                action_dim=2,
                max_episode_steps=MAZE_MAX_EPISODE_STEPS[name_maze],
            )
            tasks.append(register_task(task, overwrite=True))
    return tasks


register_pointmaze_envs()
register_pointmaze_tasks()
register_pointmaze_tasks(fixed=True)
