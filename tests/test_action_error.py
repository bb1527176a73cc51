"""study.action_error's BC reference learns: the error the TELS actor's chain is held against must be a fitted BC's."""
from __future__ import annotations

import pytest
import torch

from study.action_error import fit_bc


def test_fit_bc_learns_a_state_to_action_map_and_beats_the_mean_action():
    generator = torch.Generator().manual_seed(0)
    observation = torch.randn(2000, 6, generator=generator) * 3.0 + 1.0
    weight = torch.randn(6, 2, generator=generator) / 3.0
    action = torch.tanh(observation @ weight)
    train, test = slice(0, 1500), slice(1500, None)
    predicted = fit_bc(observation[train], action[train], steps=1500, seed=0, apply_to=observation[test])
    assert not predicted.requires_grad
    mse = (predicted - action[test]).pow(2).mean()
    mean_action = (action[train].mean(0) - action[test]).pow(2).mean()
    assert mse < 0.1 * mean_action, (mse, mean_action)


def test_masked_mse_averages_only_the_selected_entries():
    from study.action_error import _masked_mse

    action = torch.tensor([[1.0, 0.5], [-1.0, 0.0]])
    prediction = torch.tensor([[0.5, 0.5], [0.0, 1.0]])
    at_bound = action.abs() == 1
    assert _masked_mse(prediction, action, at_bound) == pytest.approx((0.25 + 1.0) / 2)
    assert _masked_mse(prediction, action, ~at_bound) == pytest.approx((0.0 + 1.0) / 2)
    assert _masked_mse(prediction, action, torch.zeros_like(at_bound)) is None
