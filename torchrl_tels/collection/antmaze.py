"""D4RL's AntMaze data, made as D4RL made it: its goal-reaching ant driven through the maze by waypoints.

The ingredients are D4RL's (``d4rl/locomotion``): the rlkit SAC goal-reaching policy
(:class:`GoalReachingAnt`, shipped in ``collection/assets``), the breadth-first waypoint controller
(:func:`next_waypoint`), the ant and maze of :class:`~torchrl_tels.envs.antmaze.AntMazeD4RLEnv`, and the
generator's noise and episode protocol (:func:`collect_antmaze`):

* a start cell drawn uniformly, the ant placed at its centre plus ``U(0, 1)`` per axis plus the env's
  reset noise; a goal per episode at its cell's centre plus ``U(0, 1) + U(0, 0.5)`` per axis;
  ``play`` sets take goals from the map's hand-picked ``g`` cells and starts from the other free cells,
  ``diverse`` sets both from all free cells (D4RL's task descriptions; its public generator does not
  show this step);
* the policy's sampled action plus ``N(0, 0.2^2)``, clipped to ``[-1, 1]``;
* 1001 steps per episode, never cut short (D4RL checks its 1000-step limit before counting a step);
* rewards and terminals relabelled against one goal drawn from the evaluation map's goal distribution:
  1 where the next torso position is within 0.5 of it.

:data:`ANTMAZE_SETS` names the four sets of the paper's Table 1.
"""
from __future__ import annotations

import importlib.resources
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from torchrl_tels.envs.antmaze import AntMazeD4RLEnv, D4RLMaze, MAZES, SUCCESS_RADIUS

__all__ = ["ANTMAZE_SETS", "AntMazeSet", "GoalReachingAnt", "cell_of", "collect_antmaze", "next_waypoint"]

#: std of the Gaussian noise D4RL's generator adds to each action
ACTION_NOISE = 0.2
#: D4RL's episode length in its AntMaze files
EPISODE_ROWS = 1001
#: the policy's waypoint direction is rescaled to this length ("in-distribution values", D4RL)
WAYPOINT_NORM = 10.0


@dataclass(frozen=True)
class AntMazeSet:
    """One of D4RL's AntMaze datasets: the maze it runs in and whether its goals are hand-picked."""

    maze: str
    play: bool

    @property
    def maze_spec(self) -> D4RLMaze:
        return MAZES[self.maze]


#: D4RL set name -> how it is made
ANTMAZE_SETS: dict[str, AntMazeSet] = {
    "medium-play": AntMazeSet("medium", play=True),
    "medium-diverse": AntMazeSet("medium", play=False),
    "large-play": AntMazeSet("large", play=True),
    "large-diverse": AntMazeSet("large", play=False),
}


class GoalReachingAnt:
    """D4RL's goal-reaching ant (rlkit SAC, 29 → 256 → 256 → 8), in NumPy.

    Its input is ``qpos[2:15]``, ``qvel`` and the direction to the waypoint rescaled to length 10; an
    action is ``tanh(mean + exp(log_std) ε)``, ``log_std`` clamped to [-20, 2].
    """

    def __init__(self, weights: dict[str, np.ndarray] | None = None) -> None:
        if weights is None:
            resource = importlib.resources.files("torchrl_tels.collection") / "assets" / "ant_goal_reaching_policy.npz"
            with importlib.resources.as_file(resource) as path, np.load(path, allow_pickle=False) as archive:
                weights = {key.rsplit("/", 1)[-1]: archive[key].astype(np.float64) for key in archive.files}
        self.weights = weights

    def __call__(self, observation: np.ndarray, direction: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A sampled action for a 29-dim D4RL antmaze observation and the direction to the waypoint."""
        w = self.weights
        direction = np.asarray(direction, np.float64)
        x = np.concatenate([observation[2:], direction / np.linalg.norm(direction) * WAYPOINT_NORM])
        h = np.maximum(w["fc0.weight"] @ x + w["fc0.bias"], 0.0)
        h = np.maximum(w["fc1.weight"] @ h + w["fc1.bias"], 0.0)
        mean = w["last_fc.weight"] @ h + w["last_fc.bias"]
        log_std = np.clip(w["last_fc_log_std.weight"] @ h + w["last_fc_log_std.bias"], -20.0, 2.0)
        return np.tanh(mean + np.exp(log_std) * rng.standard_normal(mean.shape))


def cell_of(xy) -> tuple[int, int]:
    """D4RL's cell lookup, ``(int(1 + y / 4), int(1 + x / 4))``: shifted half a cell from the cells' centres,
    kept because D4RL's controller steered with it."""
    x, y = max(float(xy[0]), 1e-4), max(float(xy[1]), 1e-4)
    return int(1 + y / 4), int(1 + x / 4)


def next_waypoint(maze: D4RLMaze, xy, goal, rng: np.random.Generator) -> np.ndarray:
    """D4RL's waypoint: the goal itself in the goal's cell, else the centre of the next cell on a shortest
    path towards it plus ``U(0, 1)`` per axis (cells by :func:`cell_of`)."""
    here, target = cell_of(xy), cell_of(goal)
    if here == target:
        return np.asarray(goal, np.float64)
    distance = maze.distances_to(target)
    row, col = here
    steps = [(distance[c], c) for c in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1))
             if c in distance]
    if not steps:  # off the map's free cells: head for the goal
        return np.asarray(goal, np.float64)
    cell = min(steps)[1]
    return maze.cell_centre(cell) + rng.uniform(0.0, 1.0, size=2)


def collect_antmaze(name: str, *, episodes: int = 100, seed: int = 0,
                    policy: GoalReachingAnt | None = None, progress: bool = True) -> dict[str, np.ndarray]:
    """Make D4RL's AntMaze set ``name`` (a key of :data:`ANTMAZE_SETS`): ``episodes`` × 1001 transitions.

    Returns D4RL's arrays (``observations``, ``actions``, ``rewards``, ``next_observations``,
    ``terminals``, ``timeouts``, ``infos/goal``; see the module docstring) and ``eval_goal``, the goal the
    rewards are relabelled against. The same ``seed`` gives the same arrays.
    """
    if name not in ANTMAZE_SETS:
        raise KeyError(f"unknown AntMaze set {name!r}; expected one of {list(ANTMAZE_SETS)}.")
    spec = ANTMAZE_SETS[name]
    maze = spec.maze_spec
    rng = np.random.default_rng(seed)
    policy = policy or GoalReachingAnt()
    goal_cells = maze.cells("g") if spec.play else maze.cells()
    start_cells = [c for c in maze.cells() if c not in goal_cells] if spec.play else maze.cells()
    eval_goal = maze.sample_goal(maze.goal_cell, rng)

    env = AntMazeD4RLEnv(spec.maze)
    rows = episodes * EPISODE_ROWS
    observations = np.empty((rows, 29), np.float32)
    next_observations = np.empty((rows, 29), np.float32)
    actions = np.empty((rows, 8), np.float32)
    goals = np.empty((rows, 2), np.float32)
    row = 0
    try:
        for episode in tqdm(range(episodes), desc=f"antmaze-{name}", disable=not progress):
            start = maze.cell_centre(start_cells[rng.integers(len(start_cells))]) + rng.uniform(0.0, 1.0, size=2)
            goal = maze.sample_goal(goal_cells[rng.integers(len(goal_cells))], rng)
            observation, _ = env.reset(seed=int(rng.integers(2**31)), options={"start": start, "goal": goal})
            for _ in range(EPISODE_ROWS):
                waypoint = next_waypoint(maze, observation[:2], goal, rng)
                action = policy(observation, waypoint - observation[:2], rng)
                action = np.clip(action + ACTION_NOISE * rng.standard_normal(8), -1.0, 1.0)
                next_observation = env.step(action)[0]  # success does not end a collection episode
                observations[row], actions[row], next_observations[row], goals[row] = (
                    observation, action, next_observation, goal)
                observation, row = next_observation, row + 1
    finally:
        env.close()
    reached = np.linalg.norm(next_observations[:, :2].astype(np.float64) - eval_goal, axis=1) <= SUCCESS_RADIUS
    timeouts = np.zeros(rows, bool)
    timeouts[EPISODE_ROWS - 1::EPISODE_ROWS] = True
    return {"observations": observations, "actions": actions, "rewards": reached.astype(np.float32),
            "next_observations": next_observations, "terminals": reached, "timeouts": timeouts,
            "infos/goal": goals, "eval_goal": eval_goal}
