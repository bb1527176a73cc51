from torchrl_tels.envs.evaluation import evaluate_policy, make_eval_env
from torchrl_tels.envs.transforms import TSIDMEncoderTransform

__all__ = ["TSIDMEncoderTransform", "evaluate_policy", "make_eval_env"]
