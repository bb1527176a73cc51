"""The Adroit hand tasks (pen, door, hammer, relocate) as D4RL scores them, in gymnasium-robotics' envs.

D4RL built its Adroit sets from the DAPG envs; gymnasium-robotics' ``AdroitHand*-v1`` are the
maintained versions of the same models, with two differences a score must undo
(``../shared/datasets/adroit/README.md``):

* **Reward sign.** Door, hammer and relocate v1 reward the palm-to-object distance with ``+0.1 * d``
  where DAPG and D4RL use ``-0.1 * d``. :class:`D4RLAdroitReward` returns ``r_v1 - 0.2 * d``, the D4RL
  reward, with ``d`` read from the simulator exactly as the env computes it.
* **Episode length.** ``AdroitHandPen-v1`` registers 200 steps; D4RL's pen episodes have 100.

Importing this module registers one Gymnasium id per task, ``torchrl_tels/Adroit<Task>D4RL-v0`` (the
D4RL reward and episode length), and the evaluation tasks on them by D4RL name
(``door-human-v1``, ``pen-expert-v1``, ... and their ``-10k``-style subsets) and Minari id
(``D4RL/door/human-v2``, ...), with D4RL's reference returns. gymnasium-robotics is imported only when
an env is built (the ``robotics`` extra installs it).

Success (D4RL's criterion): an episode succeeds when ``info["success"]`` holds on more than 25 of its
steps (pen: more than 20); :func:`~torchrl_tels.envs.evaluation.episode_success` applies it.
"""
from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from torchrl_tels.envs.robotics import import_gymnasium_robotics
from torchrl_tels.envs.tasks import register_task, Task

__all__ = ["ADROIT_TASKS", "AdroitSpec", "D4RLAdroitReward", "adroit_env_id", "register_adroit"]


@dataclass(frozen=True)
class AdroitSpec:
    """One Adroit task as D4RL defines it."""

    base_env_id: str          # the gymnasium-robotics env
    max_episode_steps: int    # D4RL's episode length
    ref_min_score: float      # D4RL REF_MIN_SCORE (random policy's return)
    ref_max_score: float      # D4RL REF_MAX_SCORE (expert's return)
    observation_dim: int
    action_dim: int
    success_steps: int        # an episode succeeds with info["success"] on more than this many steps
    palm_to: tuple[str, str] | None  # ("site" | "body", name) of the point whose palm distance v1 signs wrongly


#: D4RL's reference returns (d4rl/infos.py) and episode lengths; the distance term each v1 env signs wrongly.
ADROIT_TASKS: dict[str, AdroitSpec] = {
    "pen": AdroitSpec("AdroitHandPen-v1", 100, 96.262799, 3076.8331017826877, 45, 24, 20, None),
    "door": AdroitSpec("AdroitHandDoor-v1", 200, -56.512833, 2880.5693087298737, 39, 28, 25, ("site", "S_handle")),
    "hammer": AdroitSpec("AdroitHandHammer-v1", 200, -274.856578, 12794.134825156867, 46, 26, 25,
                         ("body", "Object")),
    "relocate": AdroitSpec("AdroitHandRelocate-v1", 200, -6.425911, 4233.877797728884, 39, 30, 25,
                           ("body", "Object")),
}
#: the D4RL dataset qualities of each task, and the Minari dataset version of them
D4RL_QUALITIES = ("human", "cloned", "expert")


def adroit_env_id(task: str) -> str:
    """The Gymnasium id of ``task``'s env with D4RL's reward and episode length."""
    return f"torchrl_tels/Adroit{task.capitalize()}D4RL-v0"


class D4RLAdroitReward(gym.Wrapper):
    """Turns a gymnasium-robotics ``AdroitHand*-v1`` env's dense reward into D4RL's.

    ``r = r_v1 - 0.2 * ||palm - object||``: v1 adds ``0.1 * d`` where D4RL subtracts it. ``d`` is the
    distance from the ``S_grasp`` site to ``palm_to`` (a site or a body position), read after the
    step, as the env reads it for its own reward. ``palm_to=None`` (pen) leaves the reward as it is.
    """

    def __init__(self, env: gym.Env, palm_to: tuple[str, str] | None) -> None:
        super().__init__(env)
        self.palm_to = palm_to
        if palm_to is not None:
            names = env.unwrapped._model_names
            self._palm = names.site_name2id["S_grasp"]
            kind, name = palm_to
            self._target = (names.site_name2id if kind == "site" else names.body_name2id)[name]

    def palm_distance(self) -> float:
        data = self.env.unwrapped.data
        target = (data.site_xpos if self.palm_to[0] == "site" else data.xpos)[self._target]
        return float(np.linalg.norm(data.site_xpos[self._palm] - target))

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self.palm_to is not None:
            reward = reward - 0.2 * self.palm_distance()
        return obs, reward, terminated, truncated, info


def make_d4rl_adroit_env(task: str, **kwargs) -> gym.Env:
    """``task``'s gymnasium-robotics env with D4RL's reward; the registration adds D4RL's time limit."""
    import_gymnasium_robotics()  # registers AdroitHand*-v1, or says which extra installs it
    spec = ADROIT_TASKS[task]
    return D4RLAdroitReward(gym.make(spec.base_env_id, max_episode_steps=None, **kwargs).unwrapped, spec.palm_to)


def register_adroit() -> list[Task]:
    """Registers each task's Gymnasium id and its evaluation tasks, by D4RL name and Minari id."""
    tasks = []
    for task, spec in ADROIT_TASKS.items():
        env_id = adroit_env_id(task)
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{__name__}:make_d4rl_adroit_env",
                         max_episode_steps=spec.max_episode_steps, kwargs={"task": task})
        for quality in D4RL_QUALITIES:
            for name in (f"{task}-{quality}-v1", f"D4RL/{task}/{quality}-v2"):
                tasks.append(register_task(Task(name, env_id, spec.ref_min_score, spec.ref_max_score,
                                                spec.observation_dim, spec.action_dim,
                                                max_episode_steps=spec.max_episode_steps,
                                                success_steps=spec.success_steps), overwrite=True))
    return tasks


register_adroit()
