"""Eq. (7)'s latent-rescaling symmetry, and the two TS-IDM options that remove it."""
from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict

from torchrl_tels.modules import TSIDM
from torchrl_tels.objectives import TSIDMLoss

OBS, ACT, ZS = 5, 2, 4
SMALL = dict(encoder_cells=(16, 12), decoder_cells=(12, 16), inverse_cells=(20, 20),
             action_decoder_cells=(16, 16), dynamics_cells=(12, 12))
TERMS = ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym")


def make_tsidm(**kwargs) -> TSIDM:
    torch.manual_seed(0)
    tsidm = TSIDM(OBS, ACT, latent_state_dim=ZS, inverse_dropout=None, **SMALL, **kwargs).double()
    tsidm.set_state_normalization(torch.randn(OBS), torch.rand(OBS) + 0.5)
    return tsidm


def batch(n=32) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(n, OBS, generator=g, dtype=torch.float64)
    return TensorDict({"observation": obs, "action": torch.randn(n, ACT, generator=g, dtype=torch.float64),
                       ("next", "observation"): obs + 0.3 * torch.randn(n, OBS, generator=g, dtype=torch.float64)},
                      [n])


@torch.no_grad()
def rescaled(tsidm: TSIDM, c: float) -> TSIDM:
    """The symmetry: φ_s → cφ_s, ψ_s(z) → ψ_s(z/c), h_inv(z, z') → h_inv(z/c, z'/c),
    h_fwd, h_rvs → c·h(z/c, z_a), built by rescaling the outer linear layers."""
    out = copy.deepcopy(tsidm)
    linear = lambda net: [m for m in net if isinstance(m, torch.nn.Linear)]
    last = linear(out.state_encoder)[-1]
    last.weight.mul_(c)
    last.bias.mul_(c)
    linear(out.state_decoder)[0].weight.div_(c)
    linear(out.inverse_dynamics)[0].weight.div_(c)  # both inputs are latent states
    for net in (out.forward_dynamics, out.reverse_dynamics):
        linear(net)[0].weight[:, :ZS].div_(c)  # the latent-state columns, not z_a's
        linear(net)[-1].weight.mul_(c)
        linear(net)[-1].bias.mul_(c)
    return out


def losses(tsidm: TSIDM, **kwargs) -> TensorDict:
    return TSIDMLoss(tsidm, beta=1.0, **kwargs)(batch())


@pytest.mark.parametrize("c", [0.5, 3.0])
def test_eq7_shrinks_dyn_and_tsym_as_c_squared(c):
    before, after = losses(make_tsidm()), losses(rescaled(make_tsidm(), c))
    for key in ("ell_rec", "ell_ode"):
        torch.testing.assert_close(after[key], before[key], rtol=1e-9, atol=0)
    for key in ("ell_dyn", "ell_tsym"):
        torch.testing.assert_close(after[key], c**2 * before[key], rtol=1e-9, atol=0)
    torch.testing.assert_close(after["latent_rms"], c * before["latent_rms"], rtol=1e-9, atol=0)
    assert not torch.allclose(after["ell_total"], before["ell_total"])


@pytest.mark.parametrize("c", [0.5, 3.0])
def test_relative_terms_make_the_rescaled_model_equal(c):
    before, after = losses(make_tsidm(), relative=True), losses(rescaled(make_tsidm(), c), relative=True)
    for key in (*TERMS, "ell_total"):
        torch.testing.assert_close(after[key], before[key], rtol=1e-9, atol=0)
    # the relative terms are the free ones over the batch's mean squared latent step
    free = losses(make_tsidm())
    step = free["latent_step_rms"] ** 2
    torch.testing.assert_close(before["ell_dyn"], free["ell_dyn"] / step, rtol=1e-9, atol=0)


@pytest.mark.parametrize("c", [0.5, 3.0])
def test_standardized_latent_makes_the_encoder_scale_a_null_direction(c):
    tsidm = make_tsidm(latent_standardization=True)
    scaled = copy.deepcopy(tsidm)
    with torch.no_grad():
        last = [m for m in scaled.state_encoder if isinstance(m, torch.nn.Linear)][-1]
        last.weight.mul_(c)
        last.bias.mul_(c)
    before, after = losses(tsidm), losses(scaled)
    for key in (*TERMS, "ell_total"):
        torch.testing.assert_close(after[key], before[key], rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(before["latent_rms"], torch.tensor(1.0, dtype=torch.float64), rtol=1e-6, atol=0)


def test_standardized_latent_acts_with_the_saved_statistics(tmp_path):
    tsidm = make_tsidm(latent_standardization=True)
    observations = batch(256)["observation"]
    tsidm.fit_latent_standardization(observations)
    z = tsidm.encode_state(observations)
    torch.testing.assert_close(z.mean(0), torch.zeros(ZS, dtype=torch.float64), rtol=0, atol=1e-10)
    torch.testing.assert_close(z.std(0), torch.ones(ZS, dtype=torch.float64), rtol=1e-10, atol=0)
    tsidm.float().save(tmp_path / "tsidm.pt")
    loaded = TSIDM.load(tmp_path / "tsidm.pt")
    assert loaded.latent_standardization
    torch.testing.assert_close(loaded.encode_state(observations.float()), z.float(), rtol=1e-5, atol=1e-5)


def test_fitting_latent_statistics_needs_a_standardized_model():
    with pytest.raises(ValueError, match="latent_standardization=False"):
        make_tsidm().fit_latent_standardization(batch()["observation"])


def test_task_table_reports_the_rollouts_realized_error_where_runs_recorded_it(monkeypatch):
    from study import latent_scale

    def run(score, realized):
        evaluations = [{"score": score, "realized_error_ratio": r} for r in realized]
        return {"final_normalized_score_mean": score, "evaluations": evaluations}

    runs = {"preset": {0: {"final_normalized_score_mean": 40.0, "evaluations": [{"score": 40.0}]}},
            "reach": {0: run(45.0, [0.2, None, 0.4]), 1: run(47.0, [0.6])}}
    monkeypatch.setattr(latent_scale, "_runs", lambda sources, task: runs.get(sources[0], {}))
    lines = latent_scale.task_table("t", arms=(("preset", ("preset",)), ("reach", ("reach",))))
    preset_row, reach_row = lines[4], lines[5]
    assert preset_row.split(" | ")[11] == "—"  # older runs did not record it
    assert reach_row.split(" | ")[11] == "0.45"  # seeds' means 0.3 and 0.6, then their mean
    assert reach_row.split(" | ")[6] == "+5.0 (1/1 up)"  # against the preset, on the seeds both have


def test_an_arm_is_compared_with_the_preset_run_on_its_own_kind_of_cpu(monkeypatch):
    from study import latent_scale

    def run(score, cpu):
        return {"final_normalized_score_mean": score, "evaluations": [{"score": score}], "machine": {"cpu": cpu}}

    runs = {"alpha1": {0: run(40.0, "Intel(R) Xeon(R) Processor, AVX-512")},
            "alpha1_epyc": {0: run(50.0, "AMD EPYC, AVX-512")},
            "arm": {0: run(53.0, "AMD EPYC, AVX-512")}}
    monkeypatch.setattr(latent_scale, "_runs", lambda sources, task: runs.get(sources[0], {}))
    lines = latent_scale.task_table("t", arms=(("preset", ("alpha1", "alpha1_epyc")), ("arm", ("arm",))))
    assert lines[4].split(" | ")[2] == "40.0"  # the preset row shows the first source
    assert lines[5].split(" | ")[6] == "+3.0 (1/1 up)"  # but the AMD arm pairs with the AMD preset
