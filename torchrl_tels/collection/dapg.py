"""The DAPG expert policies of the Adroit tasks as TorchRL actors.

D4RL's Adroit expert sets and its reference "expert" returns come from these policies (DAPG, Rajeswaran et
al. 2018, Apache-2.0). ``shared/datasets/adroit/policies/<task>-v0-dapg-policy.npz`` holds each one as plain
arrays: a tanh MLP on normalized observations, ``h = tanh(W0 x + b0)``, ``h = tanh(W1 h + b1)``,
``a = (W2 h + b2) * out_scale + out_shift`` with ``x = (obs - in_shift) / (in_scale + 1e-8)``, plus a
state-independent ``log_std`` for the sampled actions the data were recorded with.
"""
from __future__ import annotations

import os

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

__all__ = ["DAPGPolicy", "load_dapg_expert"]

_KEYS = ("W0", "b0", "W1", "b1", "W2", "b2", "in_shift", "in_scale", "out_shift", "out_scale", "log_std")


class DAPGPolicy(nn.Module):
    """An mjrl Gaussian MLP policy: its mean action, clipped to [-1, 1], or a sample with ``noise=True``."""

    def __init__(self, arrays: dict[str, np.ndarray], noise: bool = False) -> None:
        super().__init__()
        missing = [k for k in _KEYS if k not in arrays]
        if missing:
            raise ValueError(f"a DAPG policy file needs {list(_KEYS)}; missing {missing}.")
        for key in _KEYS:
            self.register_buffer(key, torch.as_tensor(np.asarray(arrays[key]), dtype=torch.float32))
        self.noise = noise

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        x = (observation.to(self.W0.dtype) - self.in_shift) / (self.in_scale + 1e-8)
        h = torch.tanh(torch.tanh(x @ self.W0.T + self.b0) @ self.W1.T + self.b1)
        action = (h @ self.W2.T + self.b2) * self.out_scale + self.out_shift
        if self.noise:
            action = action + self.log_std.exp() * torch.randn_like(action)
        return action.clamp(-1.0, 1.0)


def load_dapg_expert(path: str | os.PathLike, noise: bool = False) -> TensorDictModule:
    """The policy in ``path`` (a ``.npz`` of its arrays) as an actor reading ``"observation"``, writing ``"action"``."""
    with np.load(path) as arrays:
        return TensorDictModule(DAPGPolicy(dict(arrays), noise=noise), in_keys=["observation"], out_keys=["action"])
