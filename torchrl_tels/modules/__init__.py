from torchrl_tels.modules.actors import (
    GUIDE_KEY,
    IndependentNormal,
    LATENT_KEY,
    LatentActionHead,
    make_guide_policy,
    make_latent_value,
    make_tels_actor,
    StateEncoder,
)
from torchrl_tels.modules.tsidm import jvp, squared_norm, TSIDM

__all__ = [
    "GUIDE_KEY",
    "IndependentNormal",
    "LATENT_KEY",
    "LatentActionHead",
    "StateEncoder",
    "TSIDM",
    "jvp",
    "make_guide_policy",
    "make_latent_value",
    "make_tels_actor",
    "squared_norm",
]
