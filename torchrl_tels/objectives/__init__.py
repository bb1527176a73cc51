from torchrl_tels.objectives.tsidm import TSIDM_ABLATIONS, TSIDMLoss

__all__ = ["TSIDMLoss", "TSIDM_ABLATIONS"]
