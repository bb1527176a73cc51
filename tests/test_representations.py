"""The encoder objectives of ``benchmarks/representations.py``: their math and that they learn."""
from __future__ import annotations

import pytest
import torch
from torch import nn
from tensordict import TensorDict

from benchmarks import representations
from torchrl_tels.data import load_dataset
from torchrl_tels.modules import TSIDM

SMALL = ["tsidm.encoder_cells=[64]", "tsidm.decoder_cells=[64]", "tsidm.inverse_cells=[64]",
         "tsidm.action_decoder_cells=[64]", "tsidm.dynamics_cells=[64]"]


def test_vae_loss_is_reconstruction_plus_the_gaussian_kl():
    """Against torch.distributions: KL(N(μ, σ²) || N(0, I)) summed over dimensions, batch mean."""
    torch.manual_seed(0)
    tsidm = TSIDM(4, 2, encoder_cells=[8], decoder_cells=[8], inverse_cells=[8], action_decoder_cells=[8],
                  dynamics_cells=[8])
    log_variance_net = nn.Linear(4, 4)
    batch = TensorDict({"observation": torch.randn(32, 4)}, [32])
    s = tsidm.normalize_state(batch["observation"])
    mean, log_variance = tsidm.embed_state(s), log_variance_net(s)
    posterior = torch.distributions.Normal(mean, (0.5 * log_variance).exp())
    kl = torch.distributions.kl_divergence(posterior, torch.distributions.Normal(0.0, 1.0)).sum(-1).mean()
    torch.manual_seed(1)
    noise = torch.randn_like(mean)
    reconstruction = (tsidm.decode_state(mean + noise * (0.5 * log_variance).exp()) - s).pow(2).sum(-1).mean()
    torch.manual_seed(1)
    torch.testing.assert_close(representations.vae_loss(tsidm, batch, log_variance_net), reconstruction + kl)


@pytest.mark.parametrize("encoder", ["ae", "vae", "contrastive"])
def test_each_encoder_objective_learns(encoder):
    """200 steps lower the objective clearly below its start (mean of the last 20 vs the first 20 steps)."""
    data = load_dataset("hopper-medium-v2-10k")
    torch.set_num_threads(1)
    _, losses, stats = representations.train_encoder(encoder, data, seed=0, steps=200, overrides=SMALL)
    first, last = sum(losses[:20]) / 20, sum(losses[-20:]) / 20
    assert last < 0.9 * first, (first, last)
    assert stats["latent_rms"] > 0


def test_contrastive_encoder_finds_the_next_state():
    """After training, the positive pair ranks first among the batch far more often than chance (1/256)."""
    data = load_dataset("hopper-medium-v2-10k")
    torch.set_num_threads(1)
    tsidm, _, _ = representations.train_encoder("contrastive", data, seed=0, steps=200, overrides=SMALL)
    batch = data[torch.randperm(len(data), generator=torch.Generator().manual_seed(5))[:256]]
    with torch.no_grad():
        z = nn.functional.normalize(tsidm.encode_state(batch["observation"]), dim=-1)
        z_next = nn.functional.normalize(tsidm.encode_state(batch["next", "observation"]), dim=-1)
    accuracy = ((z @ z_next.T).argmax(-1) == torch.arange(256)).float().mean().item()
    assert accuracy > 0.2, accuracy


def test_a_standardized_copy_has_unit_latents_and_the_same_encoder_otherwise():
    """Over the data it was fitted on, each latent dimension has mean 0 and std 1, and it is the original
    φ_s(s) shifted and scaled per dimension; every other map is the original's."""
    torch.manual_seed(0)
    tsidm = TSIDM(4, 2, encoder_cells=[8], decoder_cells=[8], inverse_cells=[8], action_decoder_cells=[8],
                  dynamics_cells=[8]).eval()
    observations = 3.0 * torch.randn(500, 4) + 1.0
    copy = representations.with_standardized_latent(tsidm, observations)
    with torch.no_grad():
        raw, standardized = tsidm.encode_state(observations), copy.encode_state(observations)
    torch.testing.assert_close(standardized.mean(0), torch.zeros(4), atol=1e-5, rtol=0)
    torch.testing.assert_close(standardized.std(0), torch.ones(4), atol=1e-5, rtol=0)
    torch.testing.assert_close(standardized, (raw - raw.mean(0)) / raw.std(0), atol=1e-5, rtol=0)
    z = torch.randn(7, 4)
    torch.testing.assert_close(copy.decode_state(z), tsidm.decode_state(z))
