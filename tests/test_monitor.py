"""TSymConsistencyMonitor: its scores against a hand computation, in an env, on buffers, calibration, files, errors."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_tels.checkpoint import CheckpointError
from torchrl_tels.envs import TSymConsistencyMonitor
from torchrl_tels.envs.monitor import SCORE_TERMS
from torchrl_tels.errors import MonitorError, TelsError
from torchrl_tels.modules import TSIDM

OBS_DIM, ACTION_DIM, LATENT_DIM = 11, 3, 8  # Hopper-v4; latent != obs size to catch shape mix-ups


def small_tsidm(observation_dim: int = OBS_DIM, action_dim: int = ACTION_DIM, **kwargs) -> TSIDM:
    tsidm = TSIDM(observation_dim, action_dim, latent_state_dim=LATENT_DIM, encoder_cells=(32, 32),
                  decoder_cells=(32, 32), inverse_cells=(32, 32), action_decoder_cells=(32, 32),
                  dynamics_cells=(32, 32), **kwargs)
    # A non-trivial normalization, so a monitor that skipped it would be caught.
    tsidm.set_state_normalization(torch.linspace(-1.0, 1.0, observation_dim),
                                  torch.linspace(0.5, 2.0, observation_dim))
    return tsidm


def transitions(n: int = 256, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    observation = torch.randn(n, OBS_DIM, generator=g)
    return TensorDict({
        "observation": observation,
        "action": torch.rand(n, ACTION_DIM, generator=g) * 2 - 1,
        ("next", "observation"): observation + 0.1 * torch.randn(n, OBS_DIM, generator=g),
    }, batch_size=[n])


def hand_scores(tsidm: TSIDM, observation, action, next_observation) -> dict[str, torch.Tensor]:
    """The three scores from the TS-IDM's sub-networks, written out (no TSIDM helper methods)."""
    tsidm = tsidm.eval()
    with torch.no_grad():
        def encode(s):
            z = tsidm.state_encoder((s.float() - tsidm.obs_loc) / tsidm.obs_scale)
            if tsidm.latent_standardization:
                z = (z - tsidm.latent_loc) / tsidm.latent_scale
            return z

        z, z_next = encode(observation), encode(next_observation)
        z_a = tsidm.inverse_dynamics(torch.cat([z, z_next], -1))
        z_dot = tsidm.forward_dynamics(torch.cat([z, z_a], -1))
        reverse = tsidm.reverse_dynamics(torch.cat([z + z_dot, z_a], -1))
        return {
            "tsym_inconsistency": ((z_dot + reverse) ** 2).sum(-1),  # Eq. (6)
            "dynamics_residual": ((z + z_dot - z_next) ** 2).sum(-1),
            "action_residual": ((tsidm.action_decoder(z_a) - action.float()) ** 2).sum(-1),  # Eq. (3)
        }


def calibrated(tsidm: TSIDM | None = None, quantile: float = 0.9, **kwargs) -> TSymConsistencyMonitor:
    monitor = TSymConsistencyMonitor(tsidm or small_tsidm(), **kwargs)
    monitor.calibrate(transitions(512), quantile=quantile)
    return monitor


# ------------------------------------------------------------------ the scores
@pytest.mark.parametrize("standardized", [False, True])
def test_scores_equal_a_hand_computation_from_the_sub_networks(standardized):
    tsidm = small_tsidm(latent_standardization=standardized)
    if standardized:
        tsidm.fit_latent_standardization(torch.randn(200, OBS_DIM) * 3)
    monitor = TSymConsistencyMonitor(tsidm, flag=False)
    data = transitions()
    td = monitor(data.clone())
    expected = hand_scores(tsidm, data["observation"], data["action"], data["next", "observation"])
    for name in SCORE_TERMS:
        torch.testing.assert_close(td["next", name].squeeze(-1), expected[name])
        assert td["next", name].shape == (256, 1)
    torch.testing.assert_close(td["next", "ood_score"], td["next", "tsym_inconsistency"])
    # the three scores are different numbers, so a mixed-up key would be caught
    assert not torch.allclose(expected["tsym_inconsistency"], expected["dynamics_residual"])


def test_h_inv_dropout_is_off_even_in_train_mode():
    tsidm = small_tsidm()  # inverse_dropout=0.1: a monitor left in train mode would be random
    monitor = TSymConsistencyMonitor(tsidm, flag=False).train()
    data = transitions()
    first, second = monitor(data.clone()), monitor(data.clone())
    torch.testing.assert_close(first["next", "ood_score"], second["next", "ood_score"], rtol=0, atol=0)


def test_score_option_chooses_the_ood_score():
    monitor = TSymConsistencyMonitor(small_tsidm(), score="action_residual", flag=False)
    td = monitor(transitions())
    torch.testing.assert_close(td["next", "ood_score"], td["next", "action_residual"])
    with pytest.raises(MonitorError, match="score must be one of"):
        TSymConsistencyMonitor(small_tsidm(), score="loss")


# ----------------------------------------------------------------------- in an env
def test_env_specs_and_step_scores_follow_the_transition():
    monitor = calibrated(quantile=0.5)
    env = TransformedEnv(GymEnv("Hopper-v4"), monitor)
    env.set_seed(0)
    check_env_specs(env)
    spec = env.observation_spec
    assert spec["ood_score"].shape == (1,) and spec["ood"].dtype == torch.bool

    rollout = env.rollout(6)
    expected = hand_scores(monitor.tsidm, rollout["observation"], rollout["action"], rollout["next", "observation"])
    for name in SCORE_TERMS:
        torch.testing.assert_close(rollout["next", name].squeeze(-1), expected[name])
    torch.testing.assert_close(rollout["next", "ood"].squeeze(-1), expected["tsym_inconsistency"] > monitor.threshold)
    # the reset row carries zeros and no flag: no transition has happened yet
    assert (rollout["ood_score"][0] == 0).all() and not rollout["ood"][0].any()
    # after step 0, the root holds the previous transition's score (as any observation entry)
    torch.testing.assert_close(rollout["ood_score"][1:], rollout["next", "ood_score"][:-1])


def test_env_with_a_tsidm_for_another_env_is_refused():
    env = TransformedEnv(GymEnv("Hopper-v4"), TSymConsistencyMonitor(small_tsidm(observation_dim=17), flag=False))
    with pytest.raises(MonitorError, match=r"size 17.*another environment"):
        env.observation_spec
    env = TransformedEnv(GymEnv("Hopper-v4"), TSymConsistencyMonitor(small_tsidm(action_dim=2), flag=False))
    with pytest.raises(MonitorError, match=r"actions of size 2"):
        env.action_spec


def test_uncalibrated_flag_is_refused_and_flag_false_records_scores():
    env = TransformedEnv(GymEnv("Hopper-v4"), TSymConsistencyMonitor(small_tsidm()))
    with pytest.raises(MonitorError, match="not calibrated"):
        env.reset()
    with pytest.raises(MonitorError, match="not calibrated"):
        TSymConsistencyMonitor(small_tsidm())(transitions())
    env = TransformedEnv(GymEnv("Hopper-v4"), TSymConsistencyMonitor(small_tsidm(), flag=False))
    check_env_specs(env)
    rollout = env.rollout(3)
    assert "ood" not in rollout["next"].keys() and rollout["next", "ood_score"].shape == (3, 1)


# ----------------------------------------------------------------- replay buffers
@pytest.mark.parametrize("invert", [False, True])
def test_replay_buffer_sample_and_write_time(invert):
    monitor = calibrated()
    data = transitions(64)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=16)
    rb.append_transform(monitor.clone(), invert=invert)
    rb.extend(data)
    sample = rb.sample()
    expected = hand_scores(monitor.tsidm, sample["observation"], sample["action"], sample["next", "observation"])
    torch.testing.assert_close(sample["next", "ood_score"].squeeze(-1), expected["tsym_inconsistency"])
    torch.testing.assert_close(sample["next", "ood"].squeeze(-1), expected["tsym_inconsistency"] > monitor.threshold)


# ------------------------------------------------------------------ calibration
@pytest.mark.parametrize("quantile", [0.9, 0.99])
def test_calibration_flags_one_minus_quantile_of_the_data(quantile):
    monitor = TSymConsistencyMonitor(small_tsidm())
    data = transitions(4000, seed=1)
    threshold = monitor.calibrate(data, quantile=quantile)
    scores = hand_scores(monitor.tsidm, data["observation"], data["action"], data["next", "observation"])
    assert threshold == pytest.approx(torch.quantile(scores["tsym_inconsistency"].double(), quantile).item(), rel=1e-6)
    flagged = monitor(data.clone())["next", "ood"].float().mean().item()
    assert abs(flagged - (1 - quantile)) <= 1 / len(data) + 1e-9
    # on fresh data from the same distribution: 1 - q within four binomial standard deviations
    fresh = monitor(transitions(4000, seed=2))["next", "ood"].float().mean().item()
    assert abs(fresh - (1 - quantile)) < 4 * ((1 - quantile) * quantile / 4000) ** 0.5
    with pytest.raises(MonitorError, match=r"quantile must lie in \(0, 1\)"):
        monitor.calibrate(data, quantile=1.0)


def test_calibration_is_in_the_state_dict_and_clones_are_independent():
    monitor = calibrated(quantile=0.8)
    state = monitor.state_dict()
    assert float(state["threshold"]) == float(monitor.threshold) and float(state["quantile"]) == 0.8
    fresh = TSymConsistencyMonitor(small_tsidm())
    assert not fresh.calibrated
    fresh.load_state_dict(state)
    assert fresh.calibrated and float(fresh.threshold) == float(monitor.threshold)
    clone = monitor.clone()
    clone.calibrate(transitions(512), quantile=0.5)
    assert float(monitor.quantile) == 0.8 and float(clone.quantile) == 0.5


# ------------------------------------------------------------------- save/load
def test_save_load_round_trip(tmp_path):
    monitor = calibrated(score="dynamics_residual", dim_reduction="mean")
    monitor.save(tmp_path / "monitor.pt", metadata={"dataset": "x"})
    loaded = TSymConsistencyMonitor.load(tmp_path / "monitor.pt", observation_dim=OBS_DIM, action_dim=ACTION_DIM)
    assert loaded.score_key == "dynamics_residual" and loaded.dim_reduction == "mean"
    assert float(loaded.threshold) == float(monitor.threshold) and float(loaded.quantile) == 0.9
    assert loaded.metadata == {"dataset": "x"}
    data = transitions()
    torch.testing.assert_close(loaded(data.clone())["next"], monitor(data.clone())["next"], rtol=0, atol=0)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic: no temporary file left


def test_loading_refuses_another_tasks_monitor_and_other_files(tmp_path):
    calibrated().save(tmp_path / "monitor.pt")
    with pytest.raises(CheckpointError, match="observation_dim=11.*observation_dim=17"):
        TSymConsistencyMonitor.load(tmp_path / "monitor.pt", observation_dim=17)
    small_tsidm().save(tmp_path / "tsidm.pt")
    with pytest.raises(CheckpointError, match="torchrl_tels.monitor/v1"):
        TSymConsistencyMonitor.load(tmp_path / "tsidm.pt")
    with pytest.raises(MonitorError, match="action_dim=2 was requested"):
        TSymConsistencyMonitor(small_tsidm(), action_dim=2)


# ---------------------------------------------------------------------- bad data
def test_bad_data_is_refused_with_a_tels_error():
    monitor = calibrated()
    data = transitions(32)
    data["next", "observation"][3, 2] = float("nan")
    data["next", "observation"][5, 0] = float("inf")
    with pytest.raises(MonitorError, match=r"next observation holds NaN or inf in 2 transition"):
        monitor(data)
    wrong = transitions(8).exclude("action").set("action", torch.zeros(8, 2))
    with pytest.raises(MonitorError, match=r"action has shape \(8, 2\).*size 3"):
        monitor(wrong)
    with pytest.raises(MonitorError, match=r"no 'next' entry"):
        monitor(TensorDict({"observation": torch.zeros(2, OBS_DIM), "action": torch.zeros(2, 3)}, [2]))
    assert issubclass(MonitorError, TelsError) and issubclass(MonitorError, ValueError)


# ------------------------------------------------------- the recipe's final evaluation
def test_evaluate_records_the_monitor_along_the_episodes():
    from omegaconf import OmegaConf

    from torchrl_tels.envs import get_task, rollout_episodes
    from torchrl_tels.modules import make_guide_policy, make_tels_actor
    from torchrl_tels.trainer import evaluate

    tsidm = small_tsidm()
    env = GymEnv("Hopper-v4")
    actor = make_tels_actor(tsidm, make_guide_policy(LATENT_DIM, num_cells=(16,)), env.action_spec)
    cfg = OmegaConf.create({"seed": 0, "eval": {"episodes": 2, "max_steps": 30}})
    monitor = calibrated(tsidm, quantile=0.5)
    stats = {"latent_step_rms": 1.0, "data_action_std": 1.0}
    record = evaluate(cfg, actor, env, get_task("hopper-medium-v2-10k"), 7, stats, monitor=monitor)["monitor"]
    assert "monitor" not in evaluate(cfg, actor, env, get_task("hopper-medium-v2-10k"), 7, stats)
    # the same seeded episodes, scored here by hand
    episodes = list(rollout_episodes(actor, env, 2, seed=7, max_steps=30))
    expected = [hand_scores(tsidm, r["observation"], r["action"], r["next", "observation"])["tsym_inconsistency"]
                for r in episodes]
    assert [len(s) for s in record["scores"]] == [len(e) for e in expected]
    for scores, hand in zip(record["scores"], expected):
        torch.testing.assert_close(torch.tensor(scores), hand)
    flagged = torch.cat(expected) > monitor.threshold
    assert record["ood_fraction"] == pytest.approx(flagged.float().mean().item())
    assert record["threshold"] == float(monitor.threshold) and record["quantile"] == 0.5


# ---------------------------------------------------------- the AUROC benchmark's helpers
def test_auroc_is_the_mann_whitney_statistic_on_a_hand_computed_case():
    from benchmarks.monitor_auroc import auroc

    # negatives 1, 2, 3; positives 2, 4. Pairs (pos, neg): 2>1 win, 2=2 tie, 2<3 loss; 4 beats all three.
    # (1 + 0.5 + 0 + 3) / (2 * 3) = 0.75
    assert auroc([1, 2, 3], [2, 4]) == pytest.approx(0.75)
    assert auroc([3, 1, 2], [4, 2]) == pytest.approx(0.75)  # order does not matter
    assert auroc([0, 1], [2, 3]) == 1.0 and auroc([2, 3], [0, 1]) == 0.0 and auroc([1, 1], [1]) == 0.5
    g = torch.Generator().manual_seed(0)
    neg, pos = torch.randn(300, generator=g), torch.randn(200, generator=g) + 0.5
    brute = ((pos[:, None] > neg[None]).float() + 0.5 * (pos[:, None] == neg[None]).float()).mean().item()
    assert auroc(neg.numpy(), pos.numpy()) == pytest.approx(brute)
    with pytest.raises(ValueError, match="NaN"):
        auroc([1.0, float("nan")], [2.0])


def test_trajectory_split_keeps_whole_trajectories():
    from benchmarks.monitor_auroc import split_trajectories

    episode = torch.repeat_interleave(torch.arange(20), torch.arange(1, 21))  # lengths 1..20, 210 rows
    data = TensorDict({"episode": episode, "row": torch.arange(len(episode))}, [len(episode)])
    train, held = split_trajectories(data, 0.8, seed=0)
    assert sorted(torch.cat([train["row"], held["row"]]).tolist()) == list(range(len(episode)))
    assert not set(train["episode"].tolist()) & set(held["episode"].tolist())
    assert 0.8 * len(episode) <= len(train) < 0.8 * len(episode) + 20
