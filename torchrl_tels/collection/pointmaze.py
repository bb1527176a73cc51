"""PointMaze datasets made the D4RL ``maze2d`` way, for maze experiments.

D4RL's ``maze2d`` data is one long trajectory of a waypoint controller whose
goal is redrawn every time it is reached. This module makes the same kind of
data with Gymnasium-Robotics' ``PointMaze_{UMaze,Medium,Large}-v3`` and saves
it as a Minari dataset (with :func:`minari.create_dataset_from_buffers`, no
jax needed), readable with :func:`~torchrl_tels.data.load_dataset`.

* :class:`WaypointController`: breadth-first search over the free cells to the
  goal cell, then a PD law ``a = clip(kp (w - p) - kd v, -1, 1)`` toward the
  centre ``w`` of the next cell on the path, or toward the goal itself once in
  the goal cell. It reaches every goal of the three mazes.
* :func:`collect_pointmaze_dataset`: drives the controller (plus optional
  Gaussian action noise) in the continuing task (``continuing_task=True,
  reset_target=True``).

**Observation layout.** PointMaze observations are dicts; ``load_dataset``
concatenates their entries in the observation space's (sorted) key order, so
a dataset row's ``"observation"`` is 8 numbers::

    [0:2] achieved_goal (x, y)   [2:4] desired_goal   [4:8] observation (x, y, vx, vy)

The goal is part of the observation vector (and is also stored on its own
under ``"desired_goal"``); ``(x, y)`` sits in columns 0-1, where
:func:`~torchrl_tels.data.delete_regions` looks by default. Positions are in
Gymnasium-Robotics coordinates: 1 m cells, maze centred on the origin, rows
growing towards -y.

**Goal changes.** On the step that reaches the goal (within 0.45 m) the
environment returns the *old* goal in ``desired_goal`` and has already drawn
the new one. With ``split_at_goals=True`` (default) that step ends a Minari
episode with ``terminations = True`` and reward 1 (its stored next
observation keeps the old goal: the goal is constant within an episode, as in
the episodic evaluation task), and the next episode starts from the same
position with the new goal read from the environment. With
``split_at_goals=False`` the data is one continuous episode (as D4RL's) whose
next observation after an arrival already carries the new goal.

The evaluation environments and tasks live in :mod:`torchrl_tels.envs.pointmaze`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from torchrl_tels.collection.minari_writer import prepare_minari_dataset_id, write_minari_dataset
from torchrl_tels.envs.pointmaze import check_maze, make_pointmaze_env

__all__ = ["WaypointController", "collect_pointmaze_dataset"]


# --------------------------------------------------------------------------- #
# Controller
# --------------------------------------------------------------------------- #
class WaypointController:
    """Breadth-first-search waypoints plus a PD law, as D4RL's maze2d controller.

    Args:
        maze: a Gymnasium-Robotics ``Maze`` (``env.unwrapped.maze``), or a
            PointMaze environment to take it from.
        kp: proportional gain on the position error.
        kd: derivative gain on the velocity.

    Calling the controller with a PointMaze dict observation (``observation``
    = ``[x, y, vx, vy]``, ``desired_goal`` = ``[gx, gy]``) returns the action
    (float32, in ``[-1, 1]^2``). Paths are cached per goal cell.
    """

    def __init__(self, maze: Any, kp: float = 10.0, kd: float = 1.0) -> None:
        if isinstance(maze, gym.Env):
            maze = maze.unwrapped.maze
        self.maze = maze
        self.kp = float(kp)
        self.kd = float(kd)
        grid = maze.maze_map
        self._rows, self._cols = len(grid), len(grid[0])
        self._free = np.array(
            [[cell != 1 for cell in row] for row in grid], dtype=bool
        )
        free_cells = np.argwhere(self._free)
        self._free_cells = free_cells
        self._free_centres = np.stack(
            [maze.cell_rowcol_to_xy(cell) for cell in free_cells]
        )
        self._distances: dict[tuple[int, int], np.ndarray] = {}

    def _distance_to(self, goal_cell: tuple[int, int]) -> np.ndarray:
        """Steps from every cell to ``goal_cell`` over free cells (BFS); -1 if none."""
        distance = self._distances.get(goal_cell)
        if distance is not None:
            return distance
        distance = np.full((self._rows, self._cols), -1, dtype=np.int64)
        distance[goal_cell] = 0
        queue = deque([goal_cell])
        while queue:
            i, j = queue.popleft()
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                ni, nj = i + di, j + dj
                if (
                    0 <= ni < self._rows
                    and 0 <= nj < self._cols
                    and self._free[ni, nj]
                    and distance[ni, nj] < 0
                ):
                    distance[ni, nj] = distance[i, j] + 1
                    queue.append((ni, nj))
        self._distances[goal_cell] = distance
        return distance

    def shortest_path(self, start_cell: tuple[int, int], goal_cell: tuple[int, int]) -> list[tuple[int, int]]:
        """Cells (row, col) of a shortest path from ``start_cell`` to ``goal_cell``, both included.

        Raises:
            ValueError: a cell is a wall, or the goal cannot be reached.
        """
        start_cell, goal_cell = tuple(map(int, start_cell)), tuple(map(int, goal_cell))
        for cell in (start_cell, goal_cell):
            if not self._is_free(cell):
                raise ValueError(f"cell {cell} is not a free cell of the maze.")
        distance = self._distance_to(goal_cell)
        if distance[start_cell] < 0:
            raise ValueError(f"goal cell {goal_cell} cannot be reached from {start_cell}.")
        path = [start_cell]
        while path[-1] != goal_cell:
            path.append(self._next_cell(path[-1], distance))
        return path

    def _next_cell(self, cell: tuple[int, int], distance: np.ndarray) -> tuple[int, int]:
        """The first free neighbour of ``cell`` one BFS step closer to the goal."""
        i, j = cell
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            neighbour = (i + di, j + dj)
            if self._is_free(neighbour) and distance[neighbour] == distance[cell] - 1:
                return neighbour
        raise AssertionError("BFS distances are inconsistent")  # pragma: no cover

    def _cell(self, xy: np.ndarray) -> tuple[int, int]:
        i, j = self.maze.cell_xy_to_rowcol(xy)
        return int(i), int(j)

    def _is_free(self, cell: tuple[int, int]) -> bool:
        i, j = cell
        return 0 <= i < self._rows and 0 <= j < self._cols and bool(self._free[i, j])

    def waypoint(self, position: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Where the PD law steers: next cell centre on the path, or the goal."""
        position = np.asarray(position, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        cell, goal_cell = self._cell(position), self._cell(goal)
        if not self._is_free(goal_cell):
            raise ValueError(f"goal {goal.tolist()} is not in a free cell of the maze.")
        if not self._is_free(cell):
            # Numerically on a wall boundary: head back to the nearest free cell.
            nearest = np.argmin(np.linalg.norm(self._free_centres - position, axis=1))
            return self._free_centres[nearest].copy()
        if cell == goal_cell:
            return goal
        distance = self._distance_to(goal_cell)
        if distance[cell] < 0:
            raise ValueError(f"goal cell {goal_cell} cannot be reached from {cell}.")
        return self.maze.cell_rowcol_to_xy(np.array(self._next_cell(cell, distance)))

    def action(
        self, position: np.ndarray, velocity: np.ndarray, goal: np.ndarray
    ) -> np.ndarray:
        """PD action toward :meth:`waypoint`, clipped to ``[-1, 1]``."""
        target = self.waypoint(position, goal)
        raw = self.kp * (target - np.asarray(position)) - self.kd * np.asarray(velocity)
        return np.clip(raw, -1.0, 1.0).astype(np.float32)

    def __call__(self, observation: Mapping[str, np.ndarray]) -> np.ndarray:
        state = np.asarray(observation["observation"], dtype=np.float64)
        return self.action(state[:2], state[2:4], observation["desired_goal"])


# --------------------------------------------------------------------------- #
# Collection
# --------------------------------------------------------------------------- #
def _stack_dicts(steps: list[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.stack([np.asarray(step[key]) for step in steps]) for key in steps[0]}


def _with_goal(observation: Mapping[str, np.ndarray], goal: np.ndarray) -> dict:
    fixed = {key: np.array(value, copy=True) for key, value in observation.items()}
    fixed["desired_goal"] = np.array(goal, dtype=fixed["desired_goal"].dtype, copy=True)
    return fixed


def collect_pointmaze_dataset(
    dataset_id: str,
    maze: str = "UMaze",
    n_steps: int = 100_000,
    seed: int = 0,
    action_noise: float = 0.0,
    *,
    reward_type: str = "sparse",
    split_at_goals: bool = True,
    overwrite: bool = False,
    **dataset_metadata: Any,
):
    """Record D4RL maze2d-style waypoint-controller data as a Minari dataset.

    One continuing ``PointMaze_<maze>-v3`` run (``continuing_task=True,
    reset_target=True``) reset once with ``seed``; the controller steers to
    the current goal, which the environment redraws on arrival. See the module
    docstring for how goal changes are stored.

    Args:
        dataset_id: Minari id to write under ``MINARI_DATASETS_PATH``
            (e.g. ``"local/pointmaze/umaze-v0"``).
        maze: ``"UMaze"``, ``"Medium"`` or ``"Large"``.
        n_steps: number of transitions.
        seed: seed of the reset, the goal draws and the action noise.
        action_noise: std of Gaussian noise added to the controller's action
            (then clipped to ``[-1, 1]``); the stored action is the noisy one.
            D4RL's maze2d data used 0.5.

    Keyword Args:
        reward_type: ``"sparse"`` (1 on reaching the goal) or ``"dense"``.
        split_at_goals: end an episode (terminated) at every goal reached;
            otherwise store one continuous episode.
        overwrite: replace an existing local dataset with the same id.
        **dataset_metadata: forwarded to
            :func:`minari.create_dataset_from_buffers` (``author``,
            ``description``, ...).

    Returns:
        The new :class:`minari.MinariDataset`. Its ``eval_env`` is the
        episodic task; :data:`EVAL_ENV_IDS` has the flat-observation version.

    Raises:
        ImportError: Gymnasium-Robotics is not installed.
        ValueError: bad arguments, or an existing dataset without ``overwrite``.
    """
    from minari.data_collector.episode_buffer import EpisodeBuffer

    check_maze(maze)
    if n_steps <= 0:
        raise ValueError(f"n_steps must be positive, got {n_steps}.")
    prepare_minari_dataset_id(dataset_id, action_noise, overwrite)

    env = make_pointmaze_env(
        maze,
        continuing_task=True,
        reset_target=True,
        reward_type=reward_type,
        max_episode_steps=n_steps,
    )
    eval_env = make_pointmaze_env(maze, continuing_task=False, reward_type=reward_type)
    controller = WaypointController(env)
    noise_rng = np.random.default_rng(seed)
    base = env.unwrapped

    episodes: list[EpisodeBuffer] = []

    def close_episode(observations, actions, rewards, terminations, truncations):
        episodes.append(
            EpisodeBuffer(
                id=len(episodes),
                seed=seed if not episodes else None,
                observations=_stack_dicts(observations),
                actions=np.stack(actions).astype(np.float32),
                rewards=np.asarray(rewards, dtype=np.float64),
                terminations=np.asarray(terminations, dtype=bool),
                truncations=np.asarray(truncations, dtype=bool),
                infos={},
            )
        )

    try:
        observation, _ = env.reset(seed=seed)
        observations, actions, rewards = [observation], [], []
        terminations, truncations = [], []
        goals_reached = 0
        for step in range(n_steps):
            action = controller(observation)
            if action_noise > 0:
                noisy = action + noise_rng.normal(0.0, action_noise, action.shape)
                action = np.clip(noisy, -1.0, 1.0).astype(np.float32)
            next_observation, reward, _, _, info = env.step(action)
            last = step == n_steps - 1
            arrived = bool(info["success"])
            goals_reached += arrived
            actions.append(action)
            rewards.append(float(reward))
            # The env has already drawn the next goal; the returned dict still
            # holds the old one.
            current = _with_goal(next_observation, base.goal)
            if split_at_goals and arrived:
                observations.append(next_observation)
                terminations.append(True)
                truncations.append(False)
                close_episode(observations, actions, rewards, terminations, truncations)
                observations, actions, rewards = [current], [], []
                terminations, truncations = [], []
            else:
                observations.append(current)
                terminations.append(False)
                truncations.append(last)
            observation = current
        if actions:
            close_episode(observations, actions, rewards, terminations, truncations)

        noise_text = f" + N(0, {action_noise}^2) noise" if action_noise else ""
        dataset_metadata.setdefault("algorithm_name", "waypoint controller" + noise_text)
        dataset_metadata.setdefault(
            "description",
            f"{n_steps} steps of PointMaze_{maze}-v3 (continuing, goal redrawn on "
            f"arrival; {goals_reached} goals reached) by a BFS waypoint + PD "
            f"controller{noise_text}, seed {seed}, split_at_goals={split_at_goals}, "
            "recorded by torchrl_tels.",
        )
        return write_minari_dataset(dataset_id, episodes, env, eval_env=eval_env, **dataset_metadata)
    finally:
        env.close()
        eval_env.close()
