"""Evaluation tasks of offline datasets and D4RL normalized scores.

A :class:`Task` tells how to evaluate a policy trained on a dataset: the
Gymnasium environment to roll it out in, and the reference returns that turn
an episode return into D4RL's normalized score::

    normalized score = 100 * (return - random) / (expert - random)

Tasks are looked up by dataset name with :func:`get_task`: D4RL names
(``"hopper-medium-v2"``), their reduced-size variants (``"hopper-medium-v2-10k"``,
any ``-<n>k`` suffix) and Minari ids (``"mujoco/hopper/medium-v0"``). Add your
own with :func:`register_task`.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TypeVar

from torchrl_tels.errors import TaskError

__all__ = [
    "Task",
    "D4RL_REFERENCE_SCORES",
    "get_task",
    "list_tasks",
    "normalized_score",
    "register_task",
]


@dataclass(frozen=True)
class Task:
    """How to evaluate a policy trained on an offline dataset.

    Attributes:
        name: dataset name the task was looked up with.
        env_id: Gymnasium id of the evaluation environment.
        ref_min_score: return of a random policy (D4RL ``REF_MIN_SCORE``); ``None``
            for a task without reference scores (its results are raw returns).
        ref_max_score: return of an expert policy (D4RL ``REF_MAX_SCORE``), or ``None``.
        observation_dim: size of the (flattened) observation in the dataset, if known.
        action_dim: size of the action, if known.
        max_episode_steps: episode limit used for evaluation.
        dataset: source to pass to :func:`~torchrl_tels.data.load_dataset`
            (defaults to ``name``).
        success_steps: D4RL's success criterion, where the task has one: an episode succeeds when
            the env's ``info["success"]`` holds on more than this many steps (Adroit).
    """

    name: str
    env_id: str
    ref_min_score: float | None
    ref_max_score: float | None
    observation_dim: int | None
    action_dim: int | None
    max_episode_steps: int | None = None
    dataset: str | None = None
    success_steps: int | None = None

    @property
    def info_keys(self) -> tuple[str, ...]:
        """The env ``info`` entries an evaluation records: ``"success"`` where the task has a success criterion."""
        return ("success",) if self.success_steps is not None else ()

    @property
    def has_reference_scores(self) -> bool:
        """Whether :func:`normalized_score` is defined for this task."""
        return self.ref_min_score is not None and self.ref_max_score is not None

    def __post_init__(self) -> None:
        if (self.ref_min_score is None) != (self.ref_max_score is None):
            raise ValueError(f"Task {self.name!r}: give both reference scores or neither.")
        if self.has_reference_scores and not self.ref_max_score > self.ref_min_score:
            raise ValueError(
                f"Task {self.name!r}: ref_max_score ({self.ref_max_score}) must be "
                f"greater than ref_min_score ({self.ref_min_score})."
            )
        if self.dataset is None:
            object.__setattr__(self, "dataset", self.name)


#: D4RL reference returns (random, expert) per environment family.
D4RL_REFERENCE_SCORES: dict[str, tuple[float, float]] = {
    "hopper": (-20.272305, 3234.3),
    "halfcheetah": (-280.178953, 12135.0),
    "walker2d": (1.629008, 4592.3),
    "antmaze": (0.0, 1.0),
}

_TASKS: dict[str, Task] = {}
# Reduced-size variants: "<registered name>-<thousands>k", e.g. "-10k".
_SUBSET_SUFFIX = re.compile(r"^(?P<base>.+)-(?P<thousands>\d+)k$")


def register_task(
    task: Task, *, aliases: Iterable[str] = (), overwrite: bool = False
) -> Task:
    """Make ``task`` (and its ``aliases``) available to :func:`get_task`.

    Args:
        task: the task; it is registered under ``task.name``.

    Keyword Args:
        aliases: other names resolving to the same task (the returned task's
            ``name`` is then the alias that was asked for).
        overwrite: replace an existing registration instead of raising.

    Returns:
        ``task``.

    Raises:
        ValueError: if a name is already registered and ``overwrite`` is false.

    Examples:
        >>> task = Task("pendulum-random-v0", "Pendulum-v1", -1500.0, -150.0, 3, 1)
        >>> register_task(task) is task
        True
    """
    names = [task.name, *aliases]
    if not overwrite:
        taken = [name for name in names if name in _TASKS]
        if taken:
            raise ValueError(
                f"Task name(s) {taken} already registered; pass overwrite=True to "
                "replace them."
            )
    _TASKS[task.name] = task
    for alias in aliases:
        # An alias still loads the task's own dataset.
        _TASKS[alias] = dataclasses.replace(task, name=alias)
    return task


def list_tasks() -> list[str]:
    """Sorted names of all registered tasks (without ``-<n>k`` variants)."""
    return sorted(_TASKS)


def get_task(name: str) -> Task:
    """Return the evaluation task of a dataset.

    Args:
        name: a registered dataset name or Minari id. D4RL-style names are
            matched case-insensitively, and a ``-<n>k`` suffix
            (``"hopper-medium-v2-10k"``) resolves to the task of the full
            dataset with ``name``/``dataset`` set to the reduced one.

    Raises:
        ValueError: for an unknown name; the message lists the known ones.
    """
    task = _TASKS.get(name) or _TASKS.get(name.lower())
    if task is not None:
        return task
    match = _SUBSET_SUFFIX.match(name)
    if match is not None:
        base = _TASKS.get(match["base"]) or _TASKS.get(match["base"].lower())
        if base is not None:
            return dataclasses.replace(base, name=name, dataset=name)
    raise TaskError(
        f"Unknown task {name!r}. Known tasks (a '-10k'-style suffix is also "
        f"accepted): {', '.join(list_tasks())}. Use register_task() to add one."
    )


ScoreT = TypeVar("ScoreT")


def normalized_score(task: Task | str, episode_return: ScoreT) -> ScoreT:
    """D4RL normalized score: ``100 * (ret - random) / (expert - random)``.

    Args:
        task: a :class:`Task` or a name for :func:`get_task`.
        episode_return: an undiscounted episode return, or an array/tensor of
            them (the result has the same type).

    Examples:
        >>> normalized_score("hopper-medium-v2", 3234.3)
        100.0
    """
    if isinstance(task, str):
        task = get_task(task)
    if not task.has_reference_scores:
        raise TaskError(f"task {task.name!r} has no reference scores, so returns cannot be normalized.")
    scale = task.ref_max_score - task.ref_min_score
    return 100.0 * (episode_return - task.ref_min_score) / scale


def _register_defaults() -> None:
    # (family, gymnasium env family, obs dim, act dim)
    locomotion = (
        ("hopper", "Hopper", 11, 3),
        ("halfcheetah", "HalfCheetah", 17, 6),
        ("walker2d", "Walker2d", 17, 6),
    )
    for family, env_name, obs_dim, act_dim in locomotion:
        ref_min, ref_max = D4RL_REFERENCE_SCORES[family]
        # D4RL v2 data was recorded with the v3 MuJoCo tasks; Gymnasium's v4
        # tasks use the same models with the maintained bindings.
        for quality in ("random", "medium", "medium-replay", "medium-expert", "expert"):
            register_task(
                Task(
                    f"{family}-{quality}-v2",
                    f"{env_name}-v4",
                    ref_min,
                    ref_max,
                    obs_dim,
                    act_dim,
                    max_episode_steps=1000,
                )
            )
        # Minari's MuJoCo datasets were recorded with the v5 tasks. They carry
        # their own reference scores in their metadata; D4RL's are used here
        # so scores stay comparable with the paper.
        for quality in ("simple", "medium", "expert"):
            register_task(
                Task(
                    f"mujoco/{family}/{quality}-v0",
                    f"{env_name}-v5",
                    ref_min,
                    ref_max,
                    obs_dim,
                    act_dim,
                    max_episode_steps=1000,
                )
            )

    ref_min, ref_max = D4RL_REFERENCE_SCORES["antmaze"]
    for maze in ("umaze", "umaze-diverse"):
        # D4RL observation: torso (x, y) followed by the 27 Gymnasium-Robotics
        # dims. No stock environment has D4RL's ant dynamics: evaluation runs in
        # torchrl_tels.envs.antmaze's patched AntMaze_UMaze-v5 (maze extra).
        for version in ("v0", "v2"):
            register_task(
                Task(
                    f"antmaze-{maze}-{version}",
                    "torchrl_tels/AntMazeUMazeD4RL-v0",
                    ref_min,
                    ref_max,
                    29,
                    8,
                    max_episode_steps=700,
                )
            )
    # Minari's D4RL/antmaze/<set>-v1 ids: torchrl_tels.envs.antmaze_stock.


_register_defaults()
