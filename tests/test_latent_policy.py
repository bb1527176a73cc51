"""LatentExpectileLoss (Eq. 8), TSymGuideLoss (Eq. 9, 10) and the TELS actor (Eq. 11)."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SoftUpdate

from torchrl_tels.modules import make_guide_policy, make_latent_value, make_tels_actor, TSIDM
from torchrl_tels.objectives import LatentExpectileLoss, TSymGuideLoss, value_scale

OBS, ACT, B = 6, 2, 64
CELLS = (32, 32)


def small_tsidm() -> TSIDM:
    tsidm = TSIDM(OBS, ACT, encoder_cells=CELLS, decoder_cells=CELLS, inverse_cells=CELLS,
                  action_decoder_cells=CELLS, dynamics_cells=CELLS)
    tsidm.set_state_normalization(torch.randn(OBS), torch.rand(OBS) + 0.5)
    return tsidm.eval()


def latent_batch(tsidm: TSIDM, n: int = B, reward_scale: float = 1.0) -> TensorDict:
    obs, next_obs = torch.randn(n, OBS), torch.randn(n, OBS)
    with torch.no_grad():
        latent, next_latent = tsidm.encode_state(obs), tsidm.encode_state(next_obs)
    terminated = torch.rand(n, 1) < 0.2
    return TensorDict(
        {
            "observation": obs,
            "latent": latent,
            "next": {
                "observation": next_obs,
                "latent": next_latent,
                "reward": reward_scale * torch.randn(n, 1),
                "terminated": terminated,
                "done": terminated.clone(),
            },
        },
        [n],
    )


def total(out: TensorDict) -> torch.Tensor:
    return sum(v for k, v in out.items() if k.startswith("loss_"))


def train(loss, td, steps, lr=1e-3, params=None):
    optim = torch.optim.Adam(params if params is not None else loss.parameters(), lr=lr)
    history = []
    for _ in range(steps):
        out = loss(td)
        optim.zero_grad()
        total(out).backward()
        optim.step()
        history.append(total(out).item())
    return history


# --------------------------------------------------------------- Eq. (8)
def test_expectile_loss_matches_eq8():
    tsidm = small_tsidm()
    value = make_latent_value(tsidm.latent_state_dim, CELLS)
    loss = LatentExpectileLoss(value, expectile=0.7)
    loss.make_value_estimator(gamma=0.9)
    td = latent_batch(tsidm)
    out = loss(td)
    with torch.no_grad():
        target = td["next", "reward"].squeeze(-1) + 0.9 * (~td["next", "terminated"]).float().squeeze(-1) * value.module(
            td["next", "latent"]
        ).squeeze(-1)
        diff = target - value.module(td["latent"]).squeeze(-1)
        expected = (torch.where(diff < 0, 0.3, 0.7) * diff**2).mean()
    torch.testing.assert_close(out["loss_value"], expected)


def test_expectile_loss_decreases_and_target_follows_soft_update():
    tsidm = small_tsidm()
    value = make_latent_value(tsidm.latent_state_dim, CELLS)
    loss = LatentExpectileLoss(value, expectile=0.7)
    loss.make_value_estimator(gamma=0.99)
    updater = SoftUpdate(loss, tau=0.05)
    td = latent_batch(tsidm)
    before_target = loss.target_value_network_params.clone()
    history = train(loss, td, 150, lr=1e-2)
    assert sum(history[-5:]) < 0.5 * sum(history[:5])
    live = loss.value_network_params
    # Table 11's moving average 0.05: target <- 0.95 target + 0.05 online.
    updater.step()
    for key, target in loss.target_value_network_params.items(True, True):
        torch.testing.assert_close(target, 0.95 * before_target[key] + 0.05 * live[key].data)


@pytest.mark.parametrize("expectile", [0.0, 1.0, -0.5, float("nan")])
def test_expectile_outside_unit_interval_is_refused(expectile):
    with pytest.raises(ValueError, match=r"expectile must lie in \(0, 1\)"):
        LatentExpectileLoss(make_latent_value(OBS, CELLS), expectile=expectile)


def test_gamma_in_constructor_is_rejected_like_torchrl():
    with pytest.raises(TypeError, match="make_value_estimator"):
        LatentExpectileLoss(make_latent_value(OBS, CELLS), gamma=0.99)


# --------------------------------------------------------------- Eq. (9)
def make_guide_loss(mode, tsidm, value=None, **kwargs):
    value = value or make_latent_value(tsidm.latent_state_dim, CELLS)
    guide = make_guide_policy(tsidm.latent_state_dim, mode, CELLS)
    loss = TSymGuideLoss(guide, value, tsidm, mode=mode, **kwargs)
    loss.make_value_estimator(gamma=0.99)
    return loss, guide, value


def test_deterministic_guide_terms_match_eq9_and_c3():
    tsidm = small_tsidm()
    loss, guide, value = make_guide_loss("deterministic", tsidm, alpha=0.5, eta=5.0)
    td = latent_batch(tsidm)
    out = loss(td)
    with torch.no_grad():
        z = td["latent"]
        proposal = guide.module(z)
        lam = 0.5 / value.module(z).abs().mean()  # Appendix C.3
        next_state = (td["next", "observation"] - tsidm.obs_loc) / tsidm.obs_scale
        state_term = 5.0 * ((tsidm.state_decoder(torch.cat([proposal], -1)) - next_state) ** 2).sum(-1).mean()
        z_a = tsidm.inverse_dynamics(torch.cat([z, proposal], -1))
        fwd = tsidm.forward_dynamics(torch.cat([z, z_a], -1))
        rvs = tsidm.reverse_dynamics(torch.cat([z + fwd, z_a], -1))
        tsym = ((fwd + rvs) ** 2).sum(-1).mean()
    torch.testing.assert_close(out["lambda_alpha"], lam)
    torch.testing.assert_close(value_scale(0.5, value.module(z).squeeze(-1)), lam)
    torch.testing.assert_close(out["loss_guide_value"], -(lam * value.module(proposal)).mean())
    torch.testing.assert_close(out["loss_guide_state"], state_term)
    torch.testing.assert_close(out["loss_tsym"], tsym)


@pytest.mark.parametrize("mode", ["deterministic", "stochastic"])
def test_only_the_guide_receives_gradients(mode):
    tsidm = small_tsidm()
    loss, guide, value = make_guide_loss(mode, tsidm)
    assert {id(p) for p in loss.parameters()} == {id(p) for p in guide.parameters()}
    total(loss(latent_batch(tsidm))).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in guide.parameters() if p.ndim > 1)
    assert all(p.grad is None for p in value.parameters())
    assert all(p.grad is None for p in tsidm.parameters())


@pytest.mark.parametrize("mode", ["deterministic", "stochastic"])
def test_guide_loss_decreases_on_a_fixed_batch(mode):
    tsidm = small_tsidm()
    loss, *_ = make_guide_loss(mode, tsidm)
    history = train(loss, latent_batch(tsidm), 60, lr=1e-2)
    assert sum(history[-5:]) / 5 < sum(history[:5]) / 5 - 0.1 * abs(sum(history[:5]) / 5)


def test_guide_sees_the_current_value_network():
    tsidm = small_tsidm()
    loss, _, value = make_guide_loss("deterministic", tsidm, alpha=1.0)
    td = latent_batch(tsidm)
    before = loss(td)["lambda_alpha"]
    with torch.no_grad():
        value.module[-1].bias.add_(10.0)  # what an optimizer step on V would do, in place
    after = loss(td)["lambda_alpha"]
    torch.testing.assert_close(after, 1.0 / value.module(td["latent"]).abs().mean())
    assert not torch.allclose(before, after)


@pytest.mark.parametrize("mode", ["deterministic", "stochastic"])
def test_tsym_switch_removes_exactly_the_regularizer(mode):
    tsidm = small_tsidm()
    torch.manual_seed(1)
    with_reg, guide, value = make_guide_loss(mode, tsidm)
    without = TSymGuideLoss(guide, value, tsidm, mode=mode, tsym_regularizer=False)
    without.make_value_estimator(gamma=0.99)
    td = latent_batch(tsidm)
    a, b = with_reg(td), without(td)
    assert {k for k in set(a.keys()) - set(b.keys()) if k.startswith("loss_")} == {"loss_tsym"}
    assert set(b.keys()) == set(without.out_keys)
    for key in b.keys():
        torch.testing.assert_close(a[key], b[key])


# -------------------------------------------------------------- Eq. (10)
def test_stochastic_weights_are_clipped():
    tsidm = small_tsidm()
    loss, guide, _ = make_guide_loss("stochastic", tsidm, alpha=10.0, max_weight=50.0)
    td = latent_batch(tsidm)
    td["next", "reward"] = torch.full((B, 1), 1000.0)  # exp(10 * ~1000) overflows without the clip
    out = loss(td)
    assert out["clipped_weight_fraction"] == 1.0
    log_prob = guide.get_dist(td.clone()).log_prob(td["next", "latent"])
    torch.testing.assert_close(out["loss_guide_awr"], -(50.0 * log_prob).mean())
    assert torch.isfinite(total(out))


def test_stochastic_advantage_matches_td0():
    tsidm = small_tsidm()
    loss, _, value = make_guide_loss("stochastic", tsidm, alpha=1.0)
    td = latent_batch(tsidm)
    out = loss(td)
    with torch.no_grad():
        not_term = (~td["next", "terminated"]).float().squeeze(-1)
        adv = (td["next", "reward"].squeeze(-1) + 0.99 * not_term * value.module(td["next", "latent"]).squeeze(-1)
               - value.module(td["latent"]).squeeze(-1))
    torch.testing.assert_close(out["advantage"], adv.mean())


def test_awr_weight_statistics_match_a_direct_computation():
    from torchrl_tels.diagnostics import awr_weight_statistics, maze_cells

    tsidm = small_tsidm()
    loss, _, value = make_guide_loss("stochastic", tsidm, alpha=3.0, max_weight=5.0)
    td = latent_batch(tsidm)
    xy = torch.randn(B, 2) * 6
    stats = awr_weight_statistics(loss, td, maze_cells(xy), chunk=5)  # chunks smaller than the batch
    with torch.no_grad():
        not_term = (~td["next", "terminated"]).float().squeeze(-1)
        v = value.module(td["latent"]).squeeze(-1)
        adv = td["next", "reward"].squeeze(-1) + 0.99 * not_term * value.module(td["next", "latent"]).squeeze(-1) - v
    raw = [math.exp(3.0 * a) for a in adv.tolist()]
    w = [min(x, 5.0) for x in raw]
    assert stats["effective_sample_fraction"] == pytest.approx(sum(w) ** 2 / (len(w) * sum(x * x for x in w)),
                                                               rel=1e-5)
    assert stats["clipped_fraction"] == pytest.approx(sum(x > 5.0 for x in raw) / len(raw))
    assert 0 < stats["clipped_fraction"] < 1  # the batch has weights on both sides of the clip
    assert (stats["value_min"], stats["value_max"]) == pytest.approx((v.min().item(), v.max().item()), rel=1e-5)
    cells = [(math.floor(x / 4 + 0.5), math.floor(y / 4 + 0.5)) for x, y in xy.tolist()]
    for cell in set(cells):
        mine = [i for i, c in enumerate(cells) if c == cell]
        share = stats["regions"][f"{cell[0]},{cell[1]}"]
        assert share["data_share"] == pytest.approx(len(mine) / len(cells))
        assert share["weight_share"] == pytest.approx(sum(w[i] for i in mine) / sum(w), rel=1e-5)
    out = loss(td)  # the batch's own reading, logged while training
    assert out["effective_sample_fraction"].item() == pytest.approx(stats["effective_sample_fraction"], rel=1e-5)


# -------------------------------------------------------------- Eq. (11)
def test_actor_actions_in_bounds_and_both_forms_agree():
    from torchrl.data import Bounded

    tsidm = small_tsidm()
    with torch.no_grad():
        tsidm.action_decoder[-1].bias.fill_(50.0)  # push raw actions far outside the box
    spec = Bounded(-torch.ones(ACT), torch.ones(ACT), (ACT,))
    guide = make_guide_policy(tsidm.latent_state_dim, "deterministic", CELLS)
    from_obs = make_tels_actor(tsidm, guide, spec)
    from_latent = make_tels_actor(tsidm, guide, spec, from_latent=True)
    obs = torch.randn(B, OBS)
    a = from_obs(TensorDict({"observation": obs}, [B]))["action"]
    b = from_latent(TensorDict({"latent": tsidm.encode_state(obs).detach()}, [B]))["action"]
    torch.testing.assert_close(a, b)
    assert (a <= 1).all() and (a >= -1).all() and (a == 1).any()
    # Eq. (11) exactly, inside the bounds
    with torch.no_grad():
        z = tsidm.encode_state(obs)
        raw = tsidm.decode_action(tsidm.infer_latent_action(z, guide.module(z)))
    torch.testing.assert_close(a, raw.clamp(-1, 1))


def test_actor_keeps_dropout_off_in_train_mode():
    tsidm = TSIDM(OBS, ACT, inverse_cells=(64, 64), inverse_dropout=0.5)
    guide = make_guide_policy(tsidm.latent_state_dim, "deterministic", CELLS)
    actor = make_tels_actor(tsidm, guide)
    actor.train()
    td = TensorDict({"observation": torch.randn(B, OBS)}, [B])
    torch.testing.assert_close(actor(td.clone())["action"], actor(td.clone())["action"])


def test_actor_options_for_the_open_choices():
    """reencode_proposal feeds phi_s(psi_s(z')) to h_inv; inverse_dropout turns h_inv's dropout on."""
    tsidm = TSIDM(OBS, ACT, inverse_cells=(64, 64), inverse_dropout=0.5).eval()
    guide = make_guide_policy(tsidm.latent_state_dim, "deterministic", CELLS)
    td = TensorDict({"observation": torch.randn(B, OBS)}, [B])
    with torch.no_grad():
        z = tsidm.encode_state(td["observation"])
        proposal = tsidm.embed_state(tsidm.decode_state(guide.module(z)))
        expected = tsidm.decode_action(tsidm.infer_latent_action(z, proposal))
        reencoded = make_tels_actor(tsidm, guide, reencode_proposal=True)(td.clone())["action"]
        plain = make_tels_actor(tsidm, guide)(td.clone())["action"]
    torch.testing.assert_close(reencoded, expected)
    assert not torch.allclose(reencoded, plain)

    noisy = make_tels_actor(tsidm, guide, inverse_dropout=True)
    with torch.no_grad():
        first, second = noisy(td.clone())["action"], noisy(td.clone())["action"]
    assert not torch.allclose(first, second)
    assert not tsidm.inverse_dynamics.training  # left as it was found


def test_actor_rolls_out_in_hopper():
    from torchrl.envs import GymEnv

    env = GymEnv("Hopper-v4")
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    tsidm = TSIDM(obs_dim, act_dim, encoder_cells=CELLS, decoder_cells=CELLS, inverse_cells=CELLS,
                  action_decoder_cells=CELLS, dynamics_cells=CELLS)
    with torch.no_grad():
        tsidm.action_decoder[-1].bias.fill_(3.0)
    for mode in ("deterministic", "stochastic"):
        actor = make_tels_actor(tsidm, make_guide_policy(obs_dim, mode, CELLS), env.action_spec)
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            rollout = env.rollout(20, actor)
        actions = rollout["action"]
        assert actions.shape[-1] == act_dim and rollout.shape[0] >= 1
        assert (actions <= env.action_spec.high).all() and (actions >= env.action_spec.low).all()
        assert torch.isfinite(rollout["next", "observation"]).all()
    env.close()


def test_actor_behind_encoder_transform_matches_the_observation_actor():
    """Form 2 of the actor (guide + head behind TSIDMEncoderTransform) acts exactly like form 1."""
    from torchrl.envs import GymEnv, TransformedEnv

    from torchrl_tels.envs import TSIDMEncoderTransform

    env = GymEnv("Hopper-v4")
    tsidm = TSIDM(11, 3, encoder_cells=CELLS, decoder_cells=CELLS, inverse_cells=CELLS,
                  action_decoder_cells=CELLS, dynamics_cells=CELLS).eval()
    guide = make_guide_policy(11, "deterministic", CELLS)
    from_obs = make_tels_actor(tsidm, guide, env.action_spec)
    from_latent = make_tels_actor(tsidm, guide, env.action_spec, from_latent=True)
    latent_env = TransformedEnv(GymEnv("Hopper-v4"), TSIDMEncoderTransform(tsidm))
    env.set_seed(3)
    latent_env.set_seed(3)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        a = env.rollout(30, from_obs, break_when_any_done=False)["action"]
        b = latent_env.rollout(30, from_latent, break_when_any_done=False)["action"]
    torch.testing.assert_close(a, b)
    assert a.abs().sum() > 0


def test_saved_policy_rebuilds_the_same_actor(tmp_path):
    from torchrl_tels.modules import load_tels_actor, save_guide_policy

    tsidm = small_tsidm()
    guide = make_guide_policy(tsidm.latent_state_dim, "stochastic", CELLS)
    tsidm.save(tmp_path / "tsidm.pt")
    save_guide_policy(tmp_path / "policy.pt", guide, latent_dim=tsidm.latent_state_dim, mode="stochastic",
                      num_cells=CELLS)
    actor = make_tels_actor(tsidm, guide)
    loaded = load_tels_actor(tmp_path / "policy.pt", tmp_path / "tsidm.pt")
    td = TensorDict({"observation": torch.randn(B, OBS)}, [B])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(loaded(td.clone())["action"], actor(td.clone())["action"])


def test_saved_policy_keeps_its_actor_options(tmp_path):
    from torchrl_tels.modules import load_tels_actor, save_guide_policy

    tsidm = small_tsidm()
    guide = make_guide_policy(tsidm.latent_state_dim, "deterministic", CELLS)
    tsidm.save(tmp_path / "tsidm.pt")
    save_guide_policy(tmp_path / "policy.pt", guide, latent_dim=tsidm.latent_state_dim, mode="deterministic",
                      num_cells=CELLS, actor_options={"reencode_proposal": True})
    td = TensorDict({"observation": torch.randn(B, OBS)}, [B])
    with torch.no_grad():
        reencoded = make_tels_actor(tsidm, guide, reencode_proposal=True)(td.clone())["action"]
        plain = make_tels_actor(tsidm, guide)(td.clone())["action"]
        torch.testing.assert_close(load_tels_actor(tmp_path / "policy.pt", tsidm)(td.clone())["action"], reencoded)
        # An explicit argument wins over the saved option.
        overridden = load_tels_actor(tmp_path / "policy.pt", tsidm, reencode_proposal=False)(td.clone())["action"]
    torch.testing.assert_close(overridden, plain)


@pytest.mark.parametrize("mode", ["deterministic", "stochastic"])
def test_tsym_weight_and_reference_scale_the_guide_regularizer(mode):
    """loss_tsym = w * mean_i Eq. (6)_i / d_ref; for the deterministic guide, its share of the state term."""
    tsidm = small_tsidm()
    td = latent_batch(tsidm)
    torch.manual_seed(3)
    plain, guide, value = make_guide_loss(mode, tsidm)
    scaled = TSymGuideLoss(guide, value, tsidm, mode=mode, tsym_weight=7.0, tsym_reference=0.25)
    scaled.make_value_estimator(gamma=0.99)
    torch.manual_seed(4)
    a = plain(td)
    torch.manual_seed(4)
    b = scaled(td)
    torch.testing.assert_close(b["loss_tsym"], a["loss_tsym"] * 7.0 / 0.25)
    if mode == "deterministic":
        proposal = guide(td.clone())["guide_latent"]
        with torch.no_grad():
            z_a = tsidm.infer_latent_action(td["latent"], proposal)
            z_dot = tsidm.latent_forward(td["latent"], z_a)
            eq6 = (z_dot + tsidm.latent_reverse(td["latent"] + z_dot, z_a)).pow(2).sum(-1).mean()
        torch.testing.assert_close(a["loss_tsym"], eq6)
        torch.testing.assert_close(b["tsym_to_state_ratio"], b["loss_tsym"] / b["loss_guide_state"])
        step = (proposal - td["latent"]).pow(2).sum(-1).mean().sqrt()
        torch.testing.assert_close(a["guide_step_rms"], step)
    with pytest.raises(ValueError, match="tsym_reference"):
        TSymGuideLoss(guide, value, tsidm, mode=mode, tsym_reference=0.0)


def test_reach_term_is_the_forward_models_miss_over_the_data_step():
    """loss_reach = w * E||z + h_fwd(z, h_inv(z, g)) - g||^2 / E||z' - z||^2, and it trains the guide only."""
    tsidm = small_tsidm()
    td = latent_batch(tsidm)
    torch.manual_seed(3)
    plain, guide, value = make_guide_loss("deterministic", tsidm)
    reach = TSymGuideLoss(guide, value, tsidm, reach_weight=3.0)
    out, without = reach(td), plain(td)
    assert "loss_reach" not in without.keys() and "loss_reach" in reach.out_keys
    proposal = guide(td.clone())["guide_latent"]
    with torch.no_grad():
        z, z_next = td["latent"], td["next", "latent"]
        reached = z + tsidm.latent_forward(z, tsidm.infer_latent_action(z, proposal))
        expected = 3.0 * (reached - proposal).pow(2).sum(-1).mean() / (z_next - z).pow(2).sum(-1).mean()
    torch.testing.assert_close(out["loss_reach"], expected)
    for key in ("loss_guide_value", "loss_guide_state", "loss_tsym"):  # the other terms are Eq. (9)'s
        torch.testing.assert_close(out[key], without[key])

    # a gradient on the guide's weights, none on the frozen TS-IDM
    out["loss_reach"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in reach.guide_network_params.values(True, True))
    assert all(p.grad is None for p in tsidm.parameters())

    # a proposal the forward model reaches exactly costs nothing: a forward model that returns 0 reaches "stay put"
    still = TensorDictModule(torch.nn.Identity(), in_keys=["latent"], out_keys=["guide_latent"])
    with torch.no_grad():
        for p in tsidm.forward_dynamics.parameters():
            p.zero_()
    at_rest = TSymGuideLoss(still, value, tsidm, reach_weight=3.0, check_inputs=False)
    assert at_rest(td)["loss_reach"].item() == 0.0


def test_reach_weight_is_refused_where_it_cannot_apply():
    tsidm = small_tsidm()
    _, guide, value = make_guide_loss("deterministic", tsidm)
    with pytest.raises(ValueError, match="reach_weight"):
        TSymGuideLoss(guide, value, tsidm, reach_weight=-1.0)
    _, stochastic_guide, _ = make_guide_loss("stochastic", tsidm)
    with pytest.raises(ValueError, match="deterministic guide"):
        TSymGuideLoss(stochastic_guide, value, tsidm, mode="stochastic", reach_weight=1.0)
