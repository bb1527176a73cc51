from torchrl_tels.modules.tsidm import jvp, squared_norm, TSIDM

__all__ = ["TSIDM", "jvp", "squared_norm"]
