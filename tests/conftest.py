from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_D4RL = REPO_ROOT.parent / "shared" / "datasets" / "d4rl-10k"


def shared_file(name: str) -> Path:
    """Path of a file in ../shared/datasets/d4rl-10k, or skip the test with the reason."""
    path = SHARED_D4RL / name
    if not path.exists():
        pytest.skip(f"{path} is absent (../shared is not beside this checkout)")
    return path


@pytest.fixture
def hopper_arrays():
    with np.load(shared_file("hopper-medium-v2-10k.npz")) as data:
        return {key: data[key] for key in data.files}


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
