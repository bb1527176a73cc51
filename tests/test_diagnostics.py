"""The freeze diagnostic fires on a frozen actor and stays quiet on one that moves."""
from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_tels.data import load_dataset
from torchrl_tels.diagnostics import (action_chain_statistics, is_frozen, is_off_data, latent_statistics,
                                      rollout_statistics)
from torchrl_tels.envs import make_eval_env, rollout_episodes
from torchrl_tels.modules import LATENT_KEY, GUIDE_KEY, make_tels_actor, TSIDM

SMALL = dict(encoder_cells=(32, 32), decoder_cells=(32, 32), inverse_cells=(32, 32),
             action_decoder_cells=(32, 32), dynamics_cells=(32, 32))


class Offset(nn.Module):
    """A guide proposing z + offset: offset 0 never moves in latent space."""

    def __init__(self, offset: torch.Tensor):
        super().__init__()
        self.register_buffer("offset", offset)

    def forward(self, latent):
        return latent + self.offset


def behaviour(tsidm, offset, env):
    guide = TensorDictModule(Offset(offset), in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY])
    actor = make_tels_actor(tsidm, guide, env.action_spec)
    (rollout,) = rollout_episodes(actor, env, 1, seed=0, max_steps=60)
    return rollout_statistics(rollout)


def test_freeze_diagnostic_fires_on_a_frozen_actor():
    torch.manual_seed(0)
    data = load_dataset("hopper-medium-v2-10k")
    tsidm = TSIDM(11, 3, **SMALL)
    tsidm.fit_state_normalization(data["observation"])
    stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    data_action_std = data["action"].std(0).mean().item()
    env = make_eval_env("Hopper-v4")

    # A frozen actor: the guide proposes no step and h_inv's decoder returns one action.
    frozen_tsidm = TSIDM(11, 3, **SMALL)
    frozen_tsidm.load_state_dict(tsidm.state_dict())
    with torch.no_grad():
        frozen_tsidm.action_decoder[-1].weight.zero_()
    frozen = behaviour(frozen_tsidm, torch.zeros(11), env)
    assert frozen["guide_step_rms"] == 0.0
    assert frozen["action_std"] < 1e-6
    assert is_frozen(frozen["guide_step_rms"], frozen["action_std"], stats["latent_step_rms"], data_action_std)

    # The same model with proposals as large as the data's steps and varied actions is not frozen.
    offset = torch.full((11,), stats["latent_step_rms"] / 11**0.5)
    moving = behaviour(tsidm, offset, env)
    torch.testing.assert_close(torch.tensor(moving["guide_step_rms"]), torch.tensor(stats["latent_step_rms"]),
                               rtol=1e-4, atol=0)
    assert not is_frozen(moving["guide_step_rms"], moving["action_std"], stats["latent_step_rms"], data_action_std)
    assert not is_off_data(moving["guide_step_rms"], stats["latent_step_rms"])

    # Proposals ten times the data's step size: the opposite failure, flagged as off the data.
    runaway = behaviour(tsidm, 10 * offset, env)
    assert is_off_data(runaway["guide_step_rms"], stats["latent_step_rms"])
    assert not is_frozen(runaway["guide_step_rms"], runaway["action_std"], stats["latent_step_rms"], data_action_std)


def test_latent_statistics_match_a_direct_computation():
    torch.manual_seed(0)
    data = load_dataset("hopper-medium-v2-10k")[:500]
    tsidm = TSIDM(11, 3, **SMALL)
    stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    with torch.no_grad():
        z = tsidm.state_encoder((data["observation"] - tsidm.obs_loc) / tsidm.obs_scale)
        z_next = tsidm.state_encoder((data["next", "observation"] - tsidm.obs_loc) / tsidm.obs_scale)
    step = ((z_next - z) ** 2).sum(-1).mean().sqrt().item()
    rms = ((z - z.mean(0)) ** 2).sum(0).div(z.shape[0] - 1).mean().sqrt().item()
    assert abs(stats["latent_step_rms"] - step) < 1e-5 * step
    assert abs(stats["latent_rms"] - rms) < 1e-5 * rms


class Doubling(nn.Module):
    def forward(self, latent):
        return 2 * latent


class Oracle(nn.Module):
    """A guide that looks each latent up in a table and proposes the data's own next latent."""

    def __init__(self, latent: torch.Tensor, next_latent: torch.Tensor):
        super().__init__()
        self.register_buffer("latent", latent)
        self.register_buffer("next_latent", next_latent)

    def forward(self, latent):
        return self.next_latent[torch.cdist(latent, self.latent).argmin(-1)]


def test_action_chain_statistics_split_the_error_between_tsidm_and_guide():
    torch.manual_seed(0)
    data = load_dataset("hopper-medium-v2-10k")[:2000]
    tsidm = TSIDM(11, 3, **SMALL).eval()
    tsidm.fit_state_normalization(data["observation"])
    with torch.no_grad():
        z, z_next = tsidm.encode_state(data["observation"]), tsidm.encode_state(data["next", "observation"])
        inverse = tsidm.decode_action(tsidm.infer_latent_action(z, z_next))
    expected_inverse = (inverse - data["action"]).pow(2).mean().item()

    # A guide proposing 2 z: its step is z itself, checked against a direct computation, in batches of 300.
    doubling = TensorDictModule(Doubling(), in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY])
    stats = action_chain_statistics(make_tels_actor(tsidm, doubling), data, batch_size=300)
    with torch.no_grad():
        acted = tsidm.decode_action(tsidm.infer_latent_action(z, 2 * z))
    step, data_step = z, z_next - z
    assert stats["inverse_action_mse"] == pytest.approx(expected_inverse, rel=1e-5)
    assert stats["actor_action_mse"] == pytest.approx((acted - data["action"]).pow(2).mean().item(), rel=1e-5)
    assert stats["guide_step_ratio"] == pytest.approx(
        (step.pow(2).sum(-1).mean() / data_step.pow(2).sum(-1).mean()).sqrt().item(), rel=1e-5)
    assert stats["guide_step_cosine"] == pytest.approx(
        torch.nn.functional.cosine_similarity(step, data_step, dim=-1).mean().item(), rel=1e-5)
    assert stats["guide_error_ratio"] == pytest.approx(
        ((2 * z - z_next).pow(2).sum(-1).mean() / data_step.pow(2).sum(-1).mean()).sqrt().item(), rel=1e-5)

    # A guide that proposes the data's next latent adds no error of its own.
    oracle = TensorDictModule(Oracle(z, z_next), in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY])
    stats = action_chain_statistics(make_tels_actor(tsidm, oracle), data)
    assert stats["actor_action_mse"] == pytest.approx(stats["inverse_action_mse"], rel=1e-5)
    assert stats["guide_step_ratio"] == pytest.approx(1.0, rel=1e-5)
    assert stats["guide_step_cosine"] == pytest.approx(1.0, abs=1e-5)
    assert stats["guide_error_ratio"] == pytest.approx(0.0, abs=1e-5)

    # A guide that stays put errs by exactly the data's step.
    still = TensorDictModule(Offset(torch.zeros(z.shape[-1])), in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY])
    assert action_chain_statistics(make_tels_actor(tsidm, still), data)["guide_error_ratio"] == pytest.approx(1.0, rel=1e-5)

    # The TS-IDM's part is Eq. (11) on the true next latent, whatever the head does with proposals.
    reencoding = make_tels_actor(tsidm, oracle, reencode_proposal=True)
    assert action_chain_statistics(reencoding, data)["inverse_action_mse"] == pytest.approx(expected_inverse, rel=1e-5)


def test_action_chain_statistics_refuse_an_actor_that_is_not_a_tels_chain():
    tsidm = TSIDM(11, 3, **SMALL)
    guide = TensorDictModule(Doubling(), in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY])
    data = load_dataset("hopper-medium-v2-10k")[:10]
    for actor in (make_tels_actor(tsidm, guide, from_latent=True), guide):
        with pytest.raises(ValueError, match="needs a TELS actor that starts from observations"):
            action_chain_statistics(actor, data)


def _episode(latent: torch.Tensor, proposal: torch.Tensor):
    from tensordict import TensorDict
    return TensorDict({LATENT_KEY: latent, GUIDE_KEY: proposal, "action": torch.randn(latent.shape[0], 3)},
                      batch_size=[latent.shape[0]])


def test_realized_error_ratio_measures_how_far_the_reached_state_falls_from_the_proposal():
    import numpy as np

    torch.manual_seed(0)
    latent = torch.randn(40, 5).cumsum(0)
    reached = torch.cat([latent[1:], latent[-1:] + 7.0])  # the last proposal has no reached state; it must not count

    # A proposal the environment realizes exactly, and one twice as far along the same step.
    exact = rollout_statistics(_episode(latent, reached))
    assert exact["realized_error_ratio"] == pytest.approx(0.0, abs=1e-6)
    assert exact["realized_step_cosine"] == pytest.approx(1.0, abs=1e-6)
    overshoot = rollout_statistics(_episode(latent, latent + 2 * (reached - latent)))
    assert overshoot["realized_error_ratio"] == pytest.approx(0.5, rel=1e-5)
    assert overshoot["realized_step_cosine"] == pytest.approx(1.0, abs=1e-6)

    # Arbitrary proposals, against a NumPy computation over steps 0 .. T-2.
    proposal = latent + torch.randn(40, 5)
    z, g = latent.double().numpy(), proposal.double().numpy()
    taken, proposed = z[1:] - z[:-1], g[:-1] - z[:-1]
    expected = np.sqrt(((z[1:] - g[:-1]) ** 2).sum(-1).mean() / (proposed**2).sum(-1).mean())
    cosine = ((taken * proposed).sum(-1) / np.linalg.norm(taken, axis=-1) / np.linalg.norm(proposed, axis=-1)).mean()
    stats = rollout_statistics(_episode(latent, proposal))
    assert stats["realized_error_ratio"] == pytest.approx(expected, rel=1e-5)
    assert stats["realized_step_cosine"] == pytest.approx(cosine, rel=1e-5)

    # Undefined without a proposed step or without a second state.
    assert np.isnan(rollout_statistics(_episode(latent, latent))["realized_error_ratio"])
    assert np.isnan(rollout_statistics(_episode(latent[:1], proposal[:1]))["realized_step_cosine"])
