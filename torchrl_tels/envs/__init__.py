"""Evaluation environments and tasks: the one home of task names, env ids and reference scores.

Importing this package registers every task the library ships (D4RL locomotion, Adroit
and AntMaze, PointMaze, the point-mass task) and their Gymnasium environments.
"""
from torchrl_tels.envs.tasks import (
    D4RL_REFERENCE_SCORES,
    get_task,
    list_tasks,
    normalized_score,
    register_task,
    Task,
)
from torchrl_tels.envs import adroit, antmaze, point_mass, pointmaze  # noqa: E402,F401  (register their envs and tasks)
from torchrl_tels.envs import antmaze_stock  # noqa: E402,F401  (after pointmaze: its start and goal cells)
from torchrl_tels.envs.evaluation import (
    evaluate_episodes,
    evaluate_policy,
    make_eval_env,
    make_eval_envs,
    PolicyOnDevice,
    rollout_episodes,
)
from torchrl_tels.envs.monitor import DeploymentMonitor
from torchrl_tels.envs.transforms import TSIDMEncoderTransform

__all__ = [
    "D4RL_REFERENCE_SCORES",
    "PolicyOnDevice",
    "TSIDMEncoderTransform",
    "DeploymentMonitor",
    "Task",
    "evaluate_episodes",
    "evaluate_policy",
    "get_task",
    "list_tasks",
    "make_eval_env",
    "make_eval_envs",
    "normalized_score",
    "register_task",
    "rollout_episodes",
]
