"""D4RL's AntMaze evaluation environments (umaze, medium, large) on Gymnasium-Robotics.

No stock Gymnasium-Robotics AntMaze reproduces the dynamics D4RL's antmaze
data was recorded with: Gymnasium's ant model steps at 0.01 s with motors of
gear 150 and control range ±1, D4RL's at 0.02 s with gear 1 and range ±30.
:class:`AntMazeD4RLEnv` runs Gymnasium-Robotics' ``AntMazeEnv`` on D4RL's
evaluation maps (:data:`MAZES`) with a patched copy of Gymnasium's ``ant.xml``
(see :func:`patched_ant_xml`), so that one step from a stored state with a
stored action lands on the stored next state (median absolute error about
1e-4 per dimension on ``antmaze-umaze-v0``), and speaks D4RL's language:

* **frame**: a maze cell (row i, col j) of D4RL's map has its centre at
  ``(4 (j - 1), 4 (i - 1))``: the reset cell at the origin, y growing with the
  row. Gymnasium-Robotics centres the maze and flips y; with the map's rows
  reversed the two frames differ by a translation (:attr:`D4RLMaze.xy_offset`).
* **observation** (29,): torso ``(x, y)`` in D4RL's frame, ``qpos[2:15]``,
  ``qvel`` (the layout of D4RL's antmaze data).
* **action** (8,) in ``[-1, 1]``, multiplied by :data:`ACTION_SCALE` (30)
  before it reaches the motors, as in D4RL.
* **goal**: the centre of the map's evaluation goal cell plus
  ``U(0, 1) + U(0, 0.5)`` per axis, redrawn on every reset (D4RL's ``-v2``
  protocol; ``-v0`` draws it once per environment: ``goal_per_reset=False``).
* **start**: the model's initial ``qpos`` (torso at the origin) plus
  ``U(-0.1, 0.1)`` on all 15 position coordinates, ``qvel ~ N(0, 0.1^2)``.
* **success**: the torso is within :data:`SUCCESS_RADIUS` (0.5) of the goal
  after a step; the step's reward is 1 (else 0) and the episode terminates.
  The registered ids truncate at D4RL's limit: 700 steps (umaze), 1000
  (medium, large).

An episode's return is therefore 1 on success and 0 otherwise, and the D4RL
normalized score (reference returns 0 and 1) is the success rate times 100.
Evaluate with 50-100 episodes: the dynamics are chaotic.

Importing this module registers, without needing Gymnasium-Robotics, one
Gymnasium id per maze (:data:`ENV_IDS`) and the evaluation tasks by D4RL name
(:data:`TASK_NAMES`; their ``-<n>k`` subsets resolve to them through
:func:`~torchrl_tels.envs.get_task`). Gymnasium-Robotics is imported when an
environment is built.
"""

from __future__ import annotations

import collections
import hashlib
import os
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torchrl_tels.envs.robotics import import_gymnasium_robotics, maze_files_removed
from torchrl_tels.envs.tasks import D4RL_REFERENCE_SCORES, Task, get_task, register_task

__all__ = [
    "ACTION_SCALE",
    "ENV_ID",
    "ENV_IDS",
    "MAZES",
    "SUCCESS_RADIUS",
    "TASK_NAMES",
    "AntMazeD4RLEnv",
    "D4RLMaze",
    "import_gymnasium_robotics",
    "maze_of_task",
    "patched_ant_xml",
    "register_antmaze_env",
    "register_antmaze_tasks",
]

#: D4RL's success radius around the goal (Gymnasium-Robotics uses 0.45).
SUCCESS_RADIUS = 0.5
#: Dataset actions in [-1, 1] times this are the motor controls of D4RL's ant.
ACTION_SCALE = 30.0
#: D4RL's cell size.
CELL_SIZE = 4.0


@dataclass(frozen=True)
class D4RLMaze:
    """One of D4RL's ant mazes: its map in D4RL's row order and its evaluation protocol.

    ``rows`` spell the map: ``1`` a wall, ``0`` a free cell, ``r`` the reset
    cell, ``g`` a hand-picked goal cell of the data-collection map (the
    ``play`` sets' goals). ``goal_cell`` is the ``G`` cell of D4RL's
    evaluation (``_TEST``) map.
    """

    name: str
    rows: tuple[str, ...]
    goal_cell: tuple[int, int]
    max_episode_steps: int

    @property
    def walls(self) -> np.ndarray:
        """(rows, cols) bool, True on a wall."""
        return np.array([[c == "1" for c in row] for row in self.rows])

    def cell_centre(self, cell) -> np.ndarray:
        """The centre of cell (row, col) in D4RL's frame."""
        row, col = cell
        return CELL_SIZE * np.array([col - 1.0, row - 1.0])

    def cell_at(self, xy) -> tuple[int, int]:
        """The cell (row, col) that point ``xy`` of D4RL's frame lies in."""
        return int(round(float(xy[1]) / CELL_SIZE)) + 1, int(round(float(xy[0]) / CELL_SIZE)) + 1

    def sample_goal(self, cell, rng: np.random.Generator) -> np.ndarray:
        """A goal in ``cell`` as D4RL draws one: its centre plus ``U(0, 1) + U(0, 0.5)`` per axis."""
        return self.cell_centre(cell) + rng.uniform(0.0, 1.0, size=2) + rng.uniform(0.0, 0.5, size=2)

    def distances_to(self, target: tuple[int, int]) -> dict[tuple[int, int], int]:
        """Breadth-first step counts along the corridors from every free cell to ``target``."""
        walls = self.walls
        distance = {target: 0}
        queue = collections.deque([target])
        while queue:
            row, col = queue.popleft()
            for cell in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
                if (0 <= cell[0] < walls.shape[0] and 0 <= cell[1] < walls.shape[1]
                        and not walls[cell] and cell not in distance):
                    distance[cell] = distance[row, col] + 1
                    queue.append(cell)
        return distance

    def cells(self, marker: str | None = None) -> list[tuple[int, int]]:
        """The free cells (all of them, or those marked ``marker``), row by row."""
        return [(i, j) for i, row in enumerate(self.rows) for j, c in enumerate(row)
                if c != "1" and (marker is None or c == marker)]

    @property
    def xy_offset(self) -> np.ndarray:
        """``xy_d4rl = xy_gym + xy_offset`` for Gymnasium-Robotics' maze built on the reversed rows."""
        rows, cols = self.walls.shape
        return np.array([CELL_SIZE * cols / 2 - 1.5 * CELL_SIZE, CELL_SIZE * rows / 2 - 1.5 * CELL_SIZE])

    def gym_map(self) -> list[list[int]]:
        """The map as Gymnasium-Robotics takes it: rows reversed, 1 for a wall, 0 elsewhere."""
        return [[int(c == "1") for c in row] for row in reversed(self.rows)]


#: D4RL's maze maps (``d4rl/locomotion/maze_env.py``: ``U_MAZE``, ``BIG_MAZE``,
#: ``HARDEST_MAZE``; the walls of their ``_TEST`` maps are the same) and episode limits.
MAZES: dict[str, D4RLMaze] = {
    "umaze": D4RLMaze("umaze", ("11111", "1r001", "11101", "1g001", "11111"), (3, 1), 700),
    "medium": D4RLMaze("medium", (
        "11111111",
        "1r011001",
        "100100g1",
        "11000111",
        "10010001",
        "1g100101",
        "10001g01",
        "11111111",
    ), (6, 6), 1000),
    "large": D4RLMaze("large", (
        "111111111111",
        "1r0001g00001",
        "101101010101",
        "10000g0100g1",
        "101111011101",
        "10g101000001",
        "110101010111",
        "1001g0g10g01",
        "111111111111",
    ), (7, 9), 1000),
}
#: Gymnasium id of each maze's :class:`AntMazeD4RLEnv`.
ENV_IDS: dict[str, str] = {
    "umaze": "torchrl_tels/AntMazeUMazeD4RL-v0",
    "medium": "torchrl_tels/AntMazeMediumD4RL-v0",
    "large": "torchrl_tels/AntMazeLargeD4RL-v0",
}
#: The umaze environment's id.
ENV_ID = ENV_IDS["umaze"]
#: D4RL dataset names -> the maze their evaluation runs in.
TASK_MAZES: dict[str, str] = {
    "antmaze-umaze-v0": "umaze",
    "antmaze-umaze-v2": "umaze",
    "antmaze-umaze-diverse-v0": "umaze",
    "antmaze-umaze-diverse-v2": "umaze",
    "antmaze-medium-play-v2": "medium",
    "antmaze-medium-diverse-v2": "medium",
    "antmaze-large-play-v2": "large",
    "antmaze-large-diverse-v2": "large",
}
#: Dataset names whose evaluation task is one of these environments.
TASK_NAMES: tuple[str, ...] = tuple(TASK_MAZES)


def maze_of_task(name: str) -> D4RLMaze:
    """The maze a D4RL antmaze name (or its ``-<n>k`` subset, resolved as :func:`get_task` resolves it) evaluates
    in."""
    env_id = get_task(name).env_id
    maze = next((maze for maze, maze_env_id in ENV_IDS.items() if maze_env_id == env_id), None)
    if maze is None:
        raise KeyError(f"{name!r} is not a D4RL antmaze task; known: {list(TASK_NAMES)}.")
    return MAZES[maze]


# Patched ant model values (D4RL's ant, measured against antmaze-umaze-v0).
_TIMESTEP = "0.02"
_GEOM_SOLREF = ".02 1"
_GEOM_SOLIMP = ".8 .8 .01"
# MuJoCo >= 3 adds the margins of both geoms of a contact; 0.005 each behaves
# like D4RL's engine (0.004 and 0.006 reproduce the data clearly worse).
_GEOM_MARGIN = "0.005"
_CTRL_RANGE = f"-{ACTION_SCALE:g} {ACTION_SCALE:g}"
_GEAR = "1"


def _cache_dir() -> Path:
    root = os.environ.get("TORCHRL_TELS_CACHE") or tempfile.gettempdir()
    path = Path(root) / "torchrl_tels"
    path.mkdir(parents=True, exist_ok=True)
    return path


def patched_ant_xml() -> str:
    """Write (once) Gymnasium's ``ant.xml`` patched to D4RL's ant; return its path.

    Changes to Gymnasium's model: simulation timestep 0.02; default geom
    ``solref=".02 1" solimp=".8 .8 .01"``; every geom margin 0.005; motors with
    control range ±30 and gear 1. The maze walls added by Gymnasium-Robotics
    inherit the default geom values.

    The file goes to ``$TORCHRL_TELS_CACHE/torchrl_tels`` (default: the system
    temporary folder), named after a hash of its content, and is written
    atomically so that concurrent processes can share it.
    """
    from gymnasium.envs.mujoco import ant_v5

    source = Path(ant_v5.__file__).parent / "assets" / "ant.xml"
    root = ET.parse(source).getroot()
    option = root.find("option")
    if option is None:
        option = ET.SubElement(root, "option")
    option.set("timestep", _TIMESTEP)
    default_geom = root.find("default/geom")
    if default_geom is None:
        raise RuntimeError(f"{source} has no <default><geom>; cannot patch it.")
    default_geom.set("solref", _GEOM_SOLREF)
    default_geom.set("solimp", _GEOM_SOLIMP)
    for geom in root.iter("geom"):
        if geom is default_geom or "margin" in geom.attrib:
            geom.set("margin", _GEOM_MARGIN)
    motors = list(root.iter("motor"))
    if len(motors) != 8:
        raise RuntimeError(f"{source}: expected 8 motors, found {len(motors)}.")
    for motor in motors:
        motor.set("ctrllimited", "true")
        motor.set("ctrlrange", _CTRL_RANGE)
        motor.set("gear", _GEAR)

    content = ET.tostring(root, encoding="unicode")
    digest = hashlib.sha256(content.encode()).hexdigest()[:16]
    path = _cache_dir() / f"ant_d4rl_{digest}.xml"
    if not path.is_file():
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, suffix=".xml.tmp")
        with os.fdopen(fd, "w") as file:
            file.write(content)
        os.replace(tmp_name, path)
    return str(path)


class AntMazeD4RLEnv(gym.Env):
    """One of D4RL's ant mazes with D4RL's ant, observations and episode protocol.

    See the module docstring for the details. Build it with
    ``gym.make(ENV_IDS[maze])`` (adds the episode limit) or directly.

    Args:
        maze: a key of :data:`MAZES` (``"umaze"``, ``"medium"``, ``"large"``).
        render_mode: forwarded to Gymnasium-Robotics (``"rgb_array"``, ...).
        goal_per_reset: draw a new goal on every reset (D4RL ``-v2``); if
            false, the goal drawn on the first reset is kept (D4RL ``-v0``).
        reset_noise_scale: half-width of the uniform noise on the start
            position coordinates and std of the normal noise on the start
            velocities.

    Reset ``options``: ``{"goal": (x, y)}`` sets the goal and
    ``{"start": (x, y)}`` the torso's start before noise, both in D4RL's frame.

    Raises:
        ImportError: Gymnasium-Robotics is not installed.
        ValueError: an unknown maze.
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"], "render_fps": 10}

    def __init__(
        self,
        maze: str = "umaze",
        render_mode: str | None = None,
        *,
        goal_per_reset: bool = True,
        reset_noise_scale: float = 0.1,
    ) -> None:
        super().__init__()
        if maze not in MAZES:
            raise ValueError(f"unknown maze {maze!r}; expected one of {list(MAZES)}.")
        import_gymnasium_robotics()
        from gymnasium_robotics.envs.maze.ant_maze_v5 import AntMazeEnv

        self.maze = MAZES[maze]
        self.render_mode = render_mode
        self.goal_per_reset = goal_per_reset
        self.reset_noise_scale = float(reset_noise_scale)
        self._offset = self.maze.xy_offset
        ant_xml = patched_ant_xml()  # before the private temp folder: it must outlive the build
        with maze_files_removed():
            self._maze_env = AntMazeEnv(
                render_mode=render_mode,
                maze_map=self.maze.gym_map(),
                reward_type="sparse",
                continuing_task=True,
                reset_target=False,
                xml_file=ant_xml,
                include_cfrc_ext_in_observation=False,
                frame_skip=5,
            )
        self._ant = self._maze_env.ant_env
        model = self._ant.model
        if model.nq != 15 or model.nv != 14 or model.nu != 8:
            raise RuntimeError(
                f"unexpected ant model (nq={model.nq}, nv={model.nv}, nu={model.nu})."
            )
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(29,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(8,), dtype=np.float32)
        self._goal: np.ndarray | None = None

    # ------------------------------------------------------------------ #
    @property
    def dt(self) -> float:
        """Seconds per environment step (0.1: timestep 0.02, frame skip 5)."""
        return float(self._ant.dt)

    @property
    def model(self):
        """The MuJoCo model (patched ant in the maze)."""
        return self._ant.model

    @property
    def data(self):
        """The MuJoCo data."""
        return self._ant.data

    @property
    def goal(self) -> np.ndarray | None:
        """Current goal in D4RL coordinates (``None`` before the first reset)."""
        return None if self._goal is None else self._goal.copy()

    def sample_goal(self) -> np.ndarray:
        """Draw a goal in the maze's evaluation goal cell, as D4RL's evaluation does."""
        return self.maze.sample_goal(self.maze.goal_cell, self.np_random)

    def _set_goal(self, goal: np.ndarray) -> None:
        self._goal = np.asarray(goal, dtype=np.float64).reshape(2).copy()
        # Keep Gymnasium-Robotics' goal and target marker (rendering) in sync.
        self._maze_env.goal = self._goal - self._offset
        self._maze_env.update_target_site_pos()

    def _observation(self) -> np.ndarray:
        qpos, qvel = self._ant.data.qpos, self._ant.data.qvel
        xy = qpos[:2] + self._offset
        return np.concatenate([xy, qpos[2:], qvel]).astype(np.float32)

    def set_state_from_observation(self, observation: Any) -> None:
        """Put the simulation in the state a 29-dim D4RL observation describes.

        The observation holds the whole MuJoCo state of the ant (``qpos`` with
        the torso position in D4RL coordinates, then ``qvel``).
        """
        observation = np.asarray(observation, dtype=np.float64).reshape(-1)
        if observation.shape != (29,):
            raise ValueError(
                f"expected a 29-dim D4RL antmaze observation, got {observation.shape}."
            )
        qpos = observation[:15].copy()
        qpos[:2] -= self._offset
        self._ant.set_state(qpos, observation[15:])

    # ------------------------------------------------------------------ #
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if options.get("goal") is not None:
            self._set_goal(options["goal"])
        elif self._goal is None or self.goal_per_reset:
            self._set_goal(self.sample_goal())
        start = np.zeros(2) if options.get("start") is None else np.asarray(options["start"], np.float64)
        self._ant.reset()  # clears the MuJoCo data; the state is set below
        rng, scale = self.np_random, self.reset_noise_scale
        qpos = self._ant.init_qpos.copy()
        qpos[:2] = start - self._offset
        qpos = qpos + rng.uniform(-scale, scale, size=qpos.shape)
        qvel = self._ant.init_qvel + scale * rng.standard_normal(self._ant.model.nv)
        self._ant.set_state(qpos, qvel)
        observation = self._observation()
        distance = float(np.linalg.norm(observation[:2] - self._goal))
        info = {"goal": self.goal, "distance": distance, "success": False}
        if self.render_mode == "human":
            self.render()
        return observation, info

    def step(self, action):
        if self._goal is None:
            raise RuntimeError("call reset() before step().")
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(8), -1.0, 1.0)
        self._ant.do_simulation(action * ACTION_SCALE, self._ant.frame_skip)
        observation = self._observation()
        distance = float(np.linalg.norm(observation[:2].astype(np.float64) - self._goal))
        success = distance <= SUCCESS_RADIUS
        info = {"goal": self.goal, "distance": distance, "success": success}
        if self.render_mode == "human":
            self.render()
        return observation, float(success), success, False, info

    def render(self):
        return self._ant.render()

    def close(self) -> None:
        self._maze_env.close()
        super().close()


#: The umaze environment under its earlier name.
AntMazeUMazeD4RLEnv = AntMazeD4RLEnv


def register_antmaze_env() -> None:
    """Register each maze's id of :data:`ENV_IDS` with Gymnasium (no-op where registered).

    Needs only Gymnasium: Gymnasium-Robotics is imported when an environment
    is built.
    """
    for maze, env_id in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point=f"{__name__}:AntMazeD4RLEnv",
                kwargs={"maze": maze},
                max_episode_steps=MAZES[maze].max_episode_steps,
            )


def register_antmaze_tasks() -> list[Task]:
    """(Re-)register the evaluation tasks of :data:`TASK_NAMES` on their maze's env.

    Reference scores are D4RL's antmaze ones (0 and 1), so the normalized
    score is the success rate times 100. ``-<n>k`` variants
    (``"antmaze-medium-play-v2-100k"``) resolve to these tasks through
    :func:`~torchrl_tels.envs.get_task`. Replaces earlier registrations of the
    same names.
    """
    ref_min, ref_max = D4RL_REFERENCE_SCORES["antmaze"]
    return [
        register_task(
            Task(
                name,
                ENV_IDS[maze],
                ref_min,
                ref_max,
                observation_dim=29,
                action_dim=8,
                max_episode_steps=MAZES[maze].max_episode_steps,
            ),
            overwrite=True,
        )
        for name, maze in TASK_MAZES.items()
    ]


register_antmaze_env()
register_antmaze_tasks()
