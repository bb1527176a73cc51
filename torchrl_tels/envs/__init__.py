from torchrl_tels.envs import antmaze  # noqa: F401  (registers torchrl_tels/AntMazeUMazeD4RL-v0)
from torchrl_tels.envs import point_mass  # noqa: F401  (registers torchrl_tels/PointMassGoal-v0)
from torchrl_tels.envs.evaluation import evaluate_policy, make_eval_env, rollout_episodes
from torchrl_tels.envs.transforms import TSIDMEncoderTransform

__all__ = ["TSIDMEncoderTransform", "evaluate_policy", "make_eval_env", "rollout_episodes"]
