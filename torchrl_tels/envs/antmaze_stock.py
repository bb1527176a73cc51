"""The stock D4RL AntMaze sets by Minari id, evaluated in gymnasium-robotics' AntMaze as D4RL scores them.

Minari's ``D4RL/antmaze/<maze>-v1`` sets were recorded in gymnasium-robotics' ``AntMaze_*-v4``; their
observation is the env's dict, which :func:`~torchrl_tels.data.load_dataset` flattens (sorted keys:
``achieved_goal`` (2), ``desired_goal`` (2), ``observation`` (27)). Each id evaluates in that maze as
D4RL evaluates AntMaze: one start cell and one goal cell (the opposite ends of the longest corridor,
:data:`~torchrl_tels.envs.pointmaze.FIXED_TASK_CELLS`), the episode ending with reward 1 when the ant
reaches the goal (``continuing_task=False``) and truncated at D4RL's limit (700 steps on the U-maze,
1000 on the others). A return is then 1 on success and 0 otherwise, and with reference returns 0 and 1
the normalized score is the success rate times 100.

These envs keep Gymnasium's ant (its physics differ from D4RL's mujoco-py ant, see
:mod:`torchrl_tels.envs.antmaze`); Minari's sets were recorded with the same ant, so the data and the
evaluation agree. The shipped ``antmaze-umaze-v0-10k`` set, from D4RL itself, evaluates in
:mod:`torchrl_tels.envs.antmaze`'s patched env instead.
"""
from __future__ import annotations

from typing import Any

import gymnasium as gym

from torchrl_tels.envs.robotics import import_gymnasium_robotics, maze_files_removed
from torchrl_tels.envs.pointmaze import FIXED_TASK_CELLS
from torchrl_tels.envs.tasks import register_task, Task

__all__ = ["STOCK_ANTMAZE_SETS", "register_stock_antmaze"]

#: D4RL AntMaze set -> (gymnasium-robotics maze, D4RL's evaluation episode limit)
STOCK_ANTMAZE_SETS: dict[str, tuple[str, int]] = {
    "umaze": ("UMaze", 700),
    "umaze-diverse": ("UMaze", 700),
    "medium-play": ("Medium", 1000),
    "medium-diverse": ("Medium", 1000),
    "large-play": ("Large", 1000),
    "large-diverse": ("Large", 1000),
}
_BASE_ENV = {"UMaze": "AntMaze_UMaze-v4", "Medium": "AntMaze_Medium-v4", "Large": "AntMaze_Large-v4"}
#: flattened dict observation: achieved_goal (2) + desired_goal (2) + observation (27)
OBSERVATION_DIM, ACTION_DIM = 31, 8


def stock_env_id(maze: str) -> str:
    return f"torchrl_tels/AntMaze{maze}Fixed-v0"


def make_fixed_antmaze_env(maze: str, **kwargs: Any) -> gym.Env:
    """``AntMaze_<maze>-v4`` with D4RL's one start and one goal cell, ending on success, observation flattened."""
    import_gymnasium_robotics()
    from gymnasium_robotics.envs.maze import maps

    base = {"UMaze": maps.U_MAZE, "Medium": maps.MEDIUM_MAZE, "Large": maps.LARGE_MAZE}[maze]
    maze_map = [list(row) for row in base]
    (start_row, start_col), (goal_row, goal_col) = FIXED_TASK_CELLS[maze]
    maze_map[start_row][start_col], maze_map[goal_row][goal_col] = maps.RESET, maps.GOAL
    kwargs.setdefault("continuing_task", False)
    # The registered id adds the step limit: start from the bare environment.
    with maze_files_removed():
        env = gym.make(_BASE_ENV[maze], maze_map=maze_map, **kwargs).unwrapped
    return gym.wrappers.FlattenObservation(env)


def register_stock_antmaze() -> list[Task]:
    """Registers one evaluation env per maze and the tasks ``D4RL/antmaze/<set>-v1`` on them."""
    tasks = []
    for name, (maze, steps) in STOCK_ANTMAZE_SETS.items():
        env_id = stock_env_id(maze)
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{__name__}:make_fixed_antmaze_env", kwargs={"maze": maze},
                         max_episode_steps=steps)
        tasks.append(register_task(Task(f"D4RL/antmaze/{name}-v1", env_id, 0.0, 1.0, OBSERVATION_DIM, ACTION_DIM,
                                        max_episode_steps=steps), overwrite=True))
    return tasks


register_stock_antmaze()
