"""``proposal_cap.CappedStep``: a proposed latent step longer than the cap is scaled down onto it, in its own direction."""
from __future__ import annotations

import torch

from study.proposal_cap import CappedStep
from tests.test_diagnostics import Offset


def test_long_steps_are_cut_to_the_cap_and_short_ones_kept():
    latent = torch.randn(3, 4)
    step = torch.tensor([[3.0, 4.0, 0.0, 0.0], [0.3, 0.4, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])  # norms 5, 0.5, 0
    capped = CappedStep(Offset(step), max_step=1.0)(latent) - latent
    torch.testing.assert_close(capped[0], torch.tensor([0.6, 0.8, 0.0, 0.0]))  # norm 1, same direction
    proposal = latent + step
    capped_proposal = CappedStep(Offset(step), max_step=1.0)(latent)
    assert torch.equal(capped_proposal[1:], proposal[1:])  # within the cap: the guide's proposal, unchanged
