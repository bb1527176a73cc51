"""D4RL ``antmaze-umaze`` evaluation environment on Gymnasium-Robotics.

No stock Gymnasium-Robotics AntMaze reproduces the dynamics D4RL's antmaze
data was recorded with: Gymnasium's ant model steps at 0.01 s with motors of
gear 150 and control range ±1, D4RL's at 0.02 s with gear 1 and range ±30.
:class:`AntMazeUMazeD4RLEnv` runs ``AntMaze_UMaze-v5`` on a patched copy of
Gymnasium's ``ant.xml`` (see :func:`patched_ant_xml`) so that one step from a
stored state with a stored action lands on the stored next state (median
absolute error about 1e-4 per dimension on ``antmaze-umaze-v0``), and speaks
D4RL's language:

* **observation** (29,): torso ``(x, y)`` in D4RL's frame, then
  Gymnasium-Robotics' 27-dim ``observation`` (``qpos[2:15]``, ``qvel``).
  D4RL puts the start cell at the origin with rows growing towards +y;
  Gymnasium-Robotics centres the maze with rows growing towards -y. For the
  U-maze (symmetric under a row flip) ``xy_d4rl = xy_gym + (4, 4)``.
* **action** (8,) in ``[-1, 1]``, multiplied by :data:`ACTION_SCALE` (30)
  before it reaches the motors, as in D4RL.
* **goal**: ``(0, 8) + U(0, 1) + U(0, 0.5)`` per axis in D4RL coordinates,
  redrawn on every reset (D4RL's ``-v2`` evaluation protocol; ``-v0`` draws it
  once per environment instance: pass ``goal_per_reset=False``).
* **start**: the model's initial ``qpos`` (torso at the D4RL origin) plus
  ``U(-0.1, 0.1)`` on all 15 position coordinates, ``qvel ~ N(0, 0.1^2)``.
* **success**: the torso is within :data:`SUCCESS_RADIUS` (0.5) of the goal
  after a step; the step's reward is 1 (else 0) and the episode terminates.
  ``gym.make(ENV_ID)`` truncates at :data:`MAX_EPISODE_STEPS` (700).

An episode's return is therefore 1 on success and 0 otherwise, and the D4RL
normalized score (reference returns 0 and 1) is the success rate times 100.
Evaluate with 50-100 episodes: the dynamics are chaotic.

Importing this module registers, without needing Gymnasium-Robotics:

* the Gymnasium id :data:`ENV_ID` (``"torchrl_tels/AntMazeUMazeD4RL-v0"``);
  Gymnasium-Robotics is imported only when the environment is built, with an
  error telling how to install it (``pip install "torchrl-tels[maze]"``);
* the evaluation tasks of :data:`TASK_NAMES` (``antmaze-umaze-v0`` and its
  ``-10k`` variants, ...), pointing at :data:`ENV_ID` with reference scores
  0 and 1 (:func:`register_antmaze_tasks`, replacing earlier registrations).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torchrl_tels.envs.tasks import D4RL_REFERENCE_SCORES, Task, register_task

__all__ = [
    "ACTION_SCALE",
    "ENV_ID",
    "GOAL_CELL_D4RL",
    "MAX_EPISODE_STEPS",
    "SUCCESS_RADIUS",
    "TASK_NAMES",
    "XY_OFFSET",
    "AntMazeUMazeD4RLEnv",
    "import_gymnasium_robotics",
    "patched_ant_xml",
    "register_antmaze_env",
    "register_antmaze_tasks",
]

#: Gymnasium id of :class:`AntMazeUMazeD4RLEnv`.
ENV_ID = "torchrl_tels/AntMazeUMazeD4RL-v0"
#: D4RL's evaluation episode limit for antmaze-umaze.
MAX_EPISODE_STEPS = 700
#: D4RL's success radius around the goal (Gymnasium-Robotics uses 0.45).
SUCCESS_RADIUS = 0.5
#: Dataset actions in [-1, 1] times this are the motor controls of D4RL's ant.
ACTION_SCALE = 30.0
#: ``xy_d4rl = xy_gym + XY_OFFSET`` for the U-maze.
XY_OFFSET = np.array([4.0, 4.0])
#: Corner of the goal cell in D4RL coordinates; goals are drawn above it.
GOAL_CELL_D4RL = np.array([0.0, 8.0])
#: Dataset names whose evaluation task is this environment.
TASK_NAMES: tuple[str, ...] = (
    "antmaze-umaze-v0",
    "antmaze-umaze-v2",
    "antmaze-umaze-diverse-v0",
    "antmaze-umaze-diverse-v2",
)

#: D4RL's U-maze, rows reversed into Gymnasium-Robotics' row order (the walls
#: are symmetric under the flip): reset cell "r" at row 3, goal cell "g" at row 1.
_UMAZE_MAP = [
    [1, 1, 1, 1, 1],
    [1, "g", 0, 0, 1],
    [1, 1, 1, 0, 1],
    [1, "r", 0, 0, 1],
    [1, 1, 1, 1, 1],
]
#: Torso start (D4RL origin) in Gymnasium-Robotics coordinates.
_START_GYM = -XY_OFFSET

# Patched ant model values (D4RL's ant, measured against antmaze-umaze-v0).
_TIMESTEP = "0.02"
_GEOM_SOLREF = ".02 1"
_GEOM_SOLIMP = ".8 .8 .01"
# MuJoCo >= 3 adds the margins of both geoms of a contact; 0.005 each behaves
# like D4RL's engine (0.004 and 0.006 reproduce the data clearly worse).
_GEOM_MARGIN = "0.005"
_CTRL_RANGE = f"-{ACTION_SCALE:g} {ACTION_SCALE:g}"
_GEAR = "1"

_INSTALL_HINT = (
    'pip install "torchrl-tels[maze]"  (or: pip install gymnasium-robotics==1.4.2)'
)


def import_gymnasium_robotics():
    """Import and return :mod:`gymnasium_robotics`, or explain how to install it.

    The package prints a notification about its Adroit environments on
    import; it is silenced here (it does not concern the maze environments).

    Raises:
        ImportError: Gymnasium-Robotics is not installed; the message gives the
            pip line of the ``maze`` extra.
    """
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            import gymnasium_robotics
    except ImportError as err:
        raise ImportError(
            "The maze environments (AntMaze, PointMaze) need Gymnasium-Robotics, "
            f"which is not installed: {_INSTALL_HINT}"
        ) from err
    return gymnasium_robotics


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


class AntMazeUMazeD4RLEnv(gym.Env):
    """``antmaze-umaze`` with D4RL's ant, observations and episode protocol.

    See the module docstring for the details. Build it with
    ``gym.make(ENV_ID)`` (adds the 700-step limit) or directly.

    Args:
        render_mode: forwarded to Gymnasium-Robotics (``"rgb_array"``, ...).
        goal_per_reset: draw a new goal on every reset (D4RL ``-v2``); if
            false, the goal drawn on the first reset is kept (D4RL ``-v0``).
        reset_noise_scale: half-width of the uniform noise on the start
            position coordinates and std of the normal noise on the start
            velocities.

    Reset ``options``: ``{"goal": (x, y)}`` sets the goal in D4RL coordinates.

    Raises:
        ImportError: Gymnasium-Robotics is not installed.
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"], "render_fps": 10}

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        goal_per_reset: bool = True,
        reset_noise_scale: float = 0.1,
    ) -> None:
        super().__init__()
        import_gymnasium_robotics()
        from gymnasium_robotics.envs.maze.ant_maze_v5 import AntMazeEnv

        self.render_mode = render_mode
        self.goal_per_reset = goal_per_reset
        self.reset_noise_scale = float(reset_noise_scale)
        # Gymnasium-Robotics writes a temporary model file per build, next to
        # the system temporary folder; nothing to clean up here.
        self._maze_env = AntMazeEnv(
            render_mode=render_mode,
            maze_map=_UMAZE_MAP,
            reward_type="sparse",
            continuing_task=True,
            reset_target=False,
            xml_file=patched_ant_xml(),
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
        """The MuJoCo model (patched ant in the U-maze)."""
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
        """Draw a goal as D4RL does: ``(0, 8) + U(0, 1) + U(0, 0.5)`` per axis."""
        rng = self.np_random
        noise = rng.uniform(0.0, 1.0, size=2) + rng.uniform(0.0, 0.5, size=2)
        return np.maximum(GOAL_CELL_D4RL + noise, 0.0)

    def _set_goal(self, goal: np.ndarray) -> None:
        self._goal = np.asarray(goal, dtype=np.float64).reshape(2).copy()
        # Keep Gymnasium-Robotics' goal and target marker (rendering) in sync.
        self._maze_env.goal = self._goal - XY_OFFSET
        self._maze_env.update_target_site_pos()

    def _observation(self) -> np.ndarray:
        qpos, qvel = self._ant.data.qpos, self._ant.data.qvel
        xy = qpos[:2] + XY_OFFSET
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
        qpos[:2] -= XY_OFFSET
        self._ant.set_state(qpos, observation[15:])

    # ------------------------------------------------------------------ #
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if options.get("goal") is not None:
            self._set_goal(options["goal"])
        elif self._goal is None or self.goal_per_reset:
            self._set_goal(self.sample_goal())
        self._ant.reset()  # clears the MuJoCo data; the state is set below
        rng, scale = self.np_random, self.reset_noise_scale
        qpos = self._ant.init_qpos.copy()
        qpos[:2] = _START_GYM
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


def register_antmaze_env() -> None:
    """Register :data:`ENV_ID` with Gymnasium (no-op if already registered).

    Needs only Gymnasium: Gymnasium-Robotics is imported when the environment
    is built.
    """
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point=f"{__name__}:AntMazeUMazeD4RLEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
        )


def register_antmaze_tasks() -> list[Task]:
    """(Re-)register the evaluation tasks of :data:`TASK_NAMES` on :data:`ENV_ID`.

    Reference scores are D4RL's antmaze ones (0 and 1), so the normalized
    score is the success rate times 100. ``-<n>k`` variants
    (``"antmaze-umaze-v0-10k"``) resolve to these tasks through
    :func:`~torchrl_tels.envs.get_task`. Replaces earlier registrations of the
    same names.
    """
    ref_min, ref_max = D4RL_REFERENCE_SCORES["antmaze"]
    return [
        register_task(
            Task(
                name,
                ENV_ID,
                ref_min,
                ref_max,
                observation_dim=29,
                action_dim=8,
                max_episode_steps=MAX_EPISODE_STEPS,
            ),
            overwrite=True,
        )
        for name in TASK_NAMES
    ]


register_antmaze_env()
register_antmaze_tasks()
