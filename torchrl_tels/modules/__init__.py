from torchrl_tels.modules.actors import (
    GUIDE_KEY,
    IndependentNormal,
    LATENT_KEY,
    LatentActionHead,
    load_tels_actor,
    make_guide_policy,
    make_latent_value,
    make_tels_actor,
    save_guide_policy,
    StateEncoder,
)
from torchrl_tels.modules.detectors import DynamicsEnsemble, NearestStateDistance, fit_ensembles
from torchrl_tels.modules.tsidm import jvp, squared_norm, TSIDM

__all__ = [
    "DynamicsEnsemble",
    "GUIDE_KEY",
    "IndependentNormal",
    "LATENT_KEY",
    "LatentActionHead",
    "NearestStateDistance",
    "StateEncoder",
    "TSIDM",
    "fit_ensembles",
    "jvp",
    "load_tels_actor",
    "make_guide_policy",
    "make_latent_value",
    "make_tels_actor",
    "save_guide_policy",
    "squared_norm",
]
