from torchrl_tels.objectives.latent_expectile import expectile_loss, LatentExpectileLoss
from torchrl_tels.objectives.tsidm import TSIDM_ABLATIONS, TSIDMLoss
from torchrl_tels.objectives.tsym_guide import TSymGuideLoss, value_scale

__all__ = [
    "LatentExpectileLoss",
    "TSIDMLoss",
    "TSIDM_ABLATIONS",
    "TSymGuideLoss",
    "expectile_loss",
    "value_scale",
]
