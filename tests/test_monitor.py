"""DeploymentMonitor: each score against an independent computation, calibration that holds on new data,
the windowed alarm in an env, files, and refusals."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_tels.checkpoint import CheckpointError
from torchrl_tels.data import split_trajectories
from torchrl_tels.envs import DeploymentMonitor
from torchrl_tels.envs.monitor import conformal_threshold, running_mean, SCORE_TERMS, TSIDM_TERMS
from torchrl_tels.errors import MonitorError, TelsError
from torchrl_tels.modules import DynamicsEnsemble, NearestStateDistance, TSIDM

OBS_DIM, ACTION_DIM, LATENT_DIM = 11, 3, 8  # Hopper-v4; latent != obs size to catch shape mix-ups


def small_tsidm(observation_dim: int = OBS_DIM, action_dim: int = ACTION_DIM, **kwargs) -> TSIDM:
    tsidm = TSIDM(observation_dim, action_dim, latent_state_dim=LATENT_DIM, encoder_cells=(32, 32),
                  decoder_cells=(32, 32), inverse_cells=(32, 32), action_decoder_cells=(32, 32),
                  dynamics_cells=(32, 32), **kwargs)
    # A non-trivial normalization, so a monitor that skipped it would be caught.
    tsidm.set_state_normalization(torch.linspace(-1.0, 1.0, observation_dim),
                                  torch.linspace(0.5, 2.0, observation_dim))
    return tsidm


def linear_plant(n_trajectories: int, length: int = 50, seed: int = 0, gain: float = 1.0,
                 observation_dim: int = OBS_DIM) -> TensorDict:
    """Trajectories of s' = s + 0.1 (A s + gain B a) + noise, with random actions: a plant with known dynamics."""
    g = torch.Generator().manual_seed(1234)  # the plant is the same for every seed
    a_matrix = -0.5 * torch.eye(observation_dim) + 0.1 * torch.randn(observation_dim, observation_dim, generator=g)
    b_matrix = torch.randn(ACTION_DIM, observation_dim, generator=g)
    g = torch.Generator().manual_seed(seed)
    rows = {"observation": [], "action": [], "next": [], "episode": []}
    for e in range(n_trajectories):
        s = torch.randn(observation_dim, generator=g)
        for _ in range(length):
            a = torch.rand(ACTION_DIM, generator=g) * 2 - 1
            s_next = s + 0.1 * (s @ a_matrix + gain * a @ b_matrix) + 0.02 * torch.randn(observation_dim, generator=g)
            for key, value in zip(rows, (s, a, s_next, torch.tensor(e))):
                rows[key].append(value)
            s = s_next
    n = len(rows["episode"])
    return TensorDict({"observation": torch.stack(rows["observation"]), "action": torch.stack(rows["action"]),
                       ("next", "observation"): torch.stack(rows["next"]), "episode": torch.stack(rows["episode"])},
                      [n])


def small_monitor(data: TensorDict | None = None, **kwargs) -> DeploymentMonitor:
    data = linear_plant(8) if data is None else data
    train, held = split_trajectories(data, 0.75, seed=0)
    return DeploymentMonitor.fit(train, held, members=3, num_cells=(32, 32), steps=200, quantile=0.9,
                                 window_quantile=0.95, **kwargs)


def hand_tsidm_scores(tsidm: TSIDM, observation, action, next_observation) -> dict[str, torch.Tensor]:
    """The three T-symmetry terms from the TS-IDM's sub-networks, written out (no TSIDM helper methods)."""
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


def hand_ensemble_scores(ensemble: DynamicsEnsemble, observation, action, next_observation):
    """Each member as its own chain of nn.functional.linear, then the mean's miss and the spread."""
    s = (observation - ensemble.obs_loc) / ensemble.obs_scale
    target = (next_observation - observation - ensemble.delta_loc) / ensemble.delta_scale
    predictions = []
    for k in range(ensemble.members):
        x = torch.cat([s, action], -1)
        for i, (w, b) in enumerate(zip(ensemble.weights, ensemble.biases)):
            x = torch.nn.functional.linear(x, w[k].T, b[k, 0])
            if i < len(ensemble.weights) - 1:
                x = x.clamp_min(0)
        predictions.append(x)
    p = torch.stack(predictions)
    mean = p.mean(0)
    spread = ((p - mean) ** 2).mean(0).sum(-1)
    return ((mean - target) ** 2).sum(-1), spread


# ------------------------------------------------------------------ the scores
@pytest.mark.parametrize("standardized", [False, True])
def test_tsidm_terms_equal_a_hand_computation_from_the_sub_networks(standardized):
    tsidm = small_tsidm(latent_standardization=standardized)
    if standardized:
        tsidm.fit_latent_standardization(torch.randn(200, OBS_DIM) * 3)
    monitor = DeploymentMonitor(tsidm=tsidm, score="tsym_inconsistency", flag=False)
    data = linear_plant(2)
    td = monitor(data.clone())
    expected = hand_tsidm_scores(tsidm, data["observation"], data["action"], data["next", "observation"])
    for name in TSIDM_TERMS:
        torch.testing.assert_close(td["next", name].squeeze(-1), expected[name])
        assert td["next", name].shape == (100, 1)
    # the three scores are different numbers, so a mixed-up key would be caught
    assert not torch.allclose(expected["tsym_inconsistency"], expected["dynamics_residual"])


def test_ensemble_and_nearest_state_equal_independent_computations():
    data = linear_plant(4)
    monitor = small_monitor(data)
    o, a, o2 = data["observation"], data["action"], data["next", "observation"]
    raw = monitor.raw_scores(o, a, o2)
    residual, spread = hand_ensemble_scores(monitor.dynamics, o, a, o2)
    torch.testing.assert_close(raw["model_residual"], residual, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(raw["model_disagreement"], spread, rtol=1e-4, atol=1e-6)
    states = monitor.states
    bank = states.bank
    brute = torch.cdist((o2 - states.obs_loc) / states.obs_scale, bank).min(-1).values
    torch.testing.assert_close(raw["nearest_state"], brute, rtol=1e-4, atol=1e-4)
    # the bank holds the training states, normalized by their own mean and spread
    assert bank.mean(0).abs().max() < 1e-4 and (bank.std(0) - 1).abs().max() < 1e-3


def test_ood_score_is_the_mean_of_standardized_log_terms():
    monitor = small_monitor(linear_plant(6))
    data = linear_plant(2, seed=9)  # new states: none sits on the bank, where the distance is 0
    assert monitor.combine == ("model_residual", "nearest_state") and monitor.score_key == "combined"
    raw = monitor.raw_scores(data["observation"], data["action"], data["next", "observation"])
    u = {t: (raw[t].log() - monitor.term_loc[i]) / monitor.term_scale[i] for i, t in enumerate(monitor.terms)}
    td = monitor(data.clone())
    torch.testing.assert_close(td["next", "ood_score"].squeeze(-1), (u["model_residual"] + u["nearest_state"]) / 2)
    single = DeploymentMonitor(dynamics=monitor.dynamics, states=monitor.states, score="nearest_state", flag=False)
    single.load_state_dict(monitor.state_dict())
    torch.testing.assert_close(single(data.clone())["next", "ood_score"].squeeze(-1), u["nearest_state"])


def test_detectors_are_frozen_and_deterministic_in_train_mode():
    monitor = DeploymentMonitor(tsidm=small_tsidm(), score="tsym_inconsistency", flag=False).train()
    data = linear_plant(2)  # h_inv's dropout 0.1: a monitor left in train mode would be random
    first, second = monitor(data.clone()), monitor(data.clone())
    torch.testing.assert_close(first["next", "ood_score"], second["next", "ood_score"], rtol=0, atol=0)
    assert not any(p.requires_grad for p in monitor.parameters())


# -------------------------------------------------------------- calibration
def test_conformal_threshold_is_the_ceil_n_plus_1_q_th_smallest():
    scores = torch.tensor([5.0, 1.0, 4.0, 2.0, 3.0, 9.0, 7.0, 8.0, 6.0])  # n = 9: 1..9
    assert conformal_threshold(scores, 0.8) == 8.0  # ceil(10 * 0.8) = 8th smallest
    assert conformal_threshold(scores, 0.5) == 5.0
    assert conformal_threshold(scores, 0.95) == 9.0  # ceil(9.5) = 10 > n: the largest
    # exchangeable new scores exceed it with probability <= 1 - q (here about 0.1)
    g = torch.Generator().manual_seed(0)
    rates = [(torch.randn(20000, generator=g) > conformal_threshold(torch.randn(199, generator=g), 0.9))
             .float().mean() for _ in range(200)]
    assert 0.09 < float(torch.stack(rates).mean()) <= 0.1 + 0.005


def test_running_mean_restarts_at_each_trajectory():
    scores = torch.arange(10, dtype=torch.float64)
    trajectory = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1, 1, 1])
    expected = []
    for t in range(10):
        first = 0 if t < 6 else 6
        window = scores[max(first, t - 2): t + 1]
        expected.append(window.mean())
    torch.testing.assert_close(running_mean(scores, 3, trajectory), torch.stack(expected))
    torch.testing.assert_close(running_mean(scores, 1), scores)


@pytest.mark.parametrize("method", ["split", "cross_fit"])
def test_held_out_calibration_holds_on_new_trajectories_where_in_sample_over_alarms(method):
    data = linear_plant(24, seed=0)
    new = linear_plant(40, seed=1)  # new trajectories of the same plant
    options = {"members": 3, "num_cells": (32, 32), "steps": 400, "quantile": 0.9}
    if method == "split":
        train, held = split_trajectories(data, 0.6, seed=0)
        monitor = DeploymentMonitor.fit(train, held, **options)
    else:
        monitor = DeploymentMonitor.cross_fit(data, folds=4, **options)
    rate = monitor(new.clone())["next", "ood"].float().mean().item()
    assert 0.05 <= rate <= 0.15, rate  # nominal 0.10

    in_sample = DeploymentMonitor(dynamics=monitor.dynamics, states=monitor.states)
    in_sample.calibrate(data if method == "cross_fit" else train, quantile=0.9)
    over = in_sample(new.clone())["next", "ood"].float().mean().item()
    assert over > 0.2, over  # the detectors score their own training data low: the old calibration's fault


def test_ensemble_in_bf16_learns_the_plant_too():
    data = linear_plant(20)
    ensemble = DynamicsEnsemble(OBS_DIM, ACTION_DIM, members=3, num_cells=(64, 64))
    history = ensemble.fit(data["observation"], data["action"], data["next", "observation"], steps=600, seed=0,
                           precision="bf16")
    assert history[-1] < 0.2 * history[0]
    assert all(p.dtype == torch.float32 for p in ensemble.parameters())


def hand_fit(ensemble: DynamicsEnsemble, observation, action, next_observation, steps: int, seed: int):
    """One ensemble trained on its own, written out: its normalizations, its batches, Adam on its own loss."""
    ensemble.obs_loc, ensemble.obs_scale = observation.mean(0), observation.std(0).clamp_min(1e-6)
    delta = next_observation - observation
    ensemble.delta_loc, ensemble.delta_scale = delta.mean(0), delta.std(0).clamp_min(1e-6)
    target = (delta - ensemble.delta_loc) / ensemble.delta_scale
    generator = torch.Generator().manual_seed(seed)
    optim = torch.optim.Adam(ensemble.parameters(), lr=1e-3)
    for _ in range(steps):
        index = torch.randint(len(observation), (ensemble.members, 256), generator=generator)
        x = torch.cat([(observation[index] - ensemble.obs_loc) / ensemble.obs_scale, action[index]], -1)
        for i, (weight, bias) in enumerate(zip(ensemble.weights, ensemble.biases)):
            x = x @ weight + bias
            x = torch.relu(x) if i < len(ensemble.weights) - 1 else x
        loss = (x - target[index]).pow(2).sum(-1).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()


def test_ensembles_trained_together_each_get_the_updates_they_would_alone():
    from torchrl_tels.modules import fit_ensembles

    datasets = [linear_plant(6, seed=1), linear_plant(9, seed=2, gain=2.0)]
    members, seeds = (3, 2), (7, 8)

    def fresh(k):
        torch.manual_seed(100 + k)
        return DynamicsEnsemble(OBS_DIM, ACTION_DIM, members=members[k], num_cells=(16, 16))

    transitions = [(d["observation"], d["action"], d["next", "observation"]) for d in datasets]
    together = [fresh(0), fresh(1)]
    fit_ensembles(together, transitions, seeds=seeds, steps=30)
    for k, ensemble in enumerate(together):
        alone = fresh(k)
        hand_fit(alone, *transitions[k], steps=30, seed=seeds[k])
        assert not torch.allclose(alone.weights[0], fresh(k).weights[0])  # it trained
        for name, value in alone.state_dict().items():
            torch.testing.assert_close(ensemble.state_dict()[name], value, rtol=1e-5, atol=1e-6, msg=name)
    with pytest.raises(ValueError, match="one seed per ensemble"):
        fit_ensembles(together, transitions, seeds=seeds[:1], steps=1)
    with pytest.raises(ValueError, match="one architecture"):
        fit_ensembles([fresh(0), DynamicsEnsemble(OBS_DIM, ACTION_DIM, num_cells=(8,))], transitions, seeds=seeds,
                      steps=1)


def test_ensemble_learns_the_plant_and_a_changed_plant_scores_higher():
    from benchmarks.monitor_benchmark import auroc

    data = linear_plant(20)
    ensemble = DynamicsEnsemble(OBS_DIM, ACTION_DIM, members=3, num_cells=(64, 64))
    history = ensemble.fit(data["observation"], data["action"], data["next", "observation"], steps=600, seed=0)
    assert history[-1] < 0.2 * history[0]
    same, changed = linear_plant(10, seed=5), linear_plant(10, seed=5, gain=1.5)
    with torch.no_grad():
        same_r, _ = ensemble.scores(same["observation"], same["action"], same["next", "observation"])
        changed_r, _ = ensemble.scores(changed["observation"], changed["action"], changed["next", "observation"])
    assert auroc(same_r.numpy(), changed_r.numpy()) > 0.9
    with pytest.raises(ValueError, match="precision must be 'fp32' or 'bf16'"):
        ensemble.fit(data["observation"], data["action"], data["next", "observation"], steps=1, precision="fp16")
    # over windows of 20 steps the change is plainer still
    trajectory = same["episode"]
    assert auroc(running_mean(same_r, 20, trajectory).numpy()[19::20],
                 running_mean(changed_r, 20, trajectory).numpy()[19::20]) == 1.0


# ----------------------------------------------------------------------- in an env
def test_env_specs_window_and_alarm_follow_the_episode():
    from torchrl_tels.data import load_dataset

    data = load_dataset("hopper-medium-v2-10k")[:3000]
    monitor = small_monitor(data, window=5)
    env = TransformedEnv(GymEnv("Hopper-v4"), monitor)
    env.set_seed(0)
    check_env_specs(env)
    spec = env.observation_spec
    assert spec["ood_window"].shape == (1,) and spec["ood_alarm"].dtype == torch.bool
    assert spec["ood_recent"].shape == (5,)

    rollout = env.rollout(40, break_when_any_done=False)  # random actions: the hopper falls and the env resets
    nxt = rollout["next"]
    done = nxt["done"].squeeze(-1)
    assert done[:-1].any()
    trajectory = torch.cat([torch.zeros(1, dtype=torch.long), done[:-1].long().cumsum(0)])
    expected = monitor.scores(rollout["observation"], rollout["action"], nxt["observation"])
    for name in (*SCORE_TERMS[3:], "ood_score"):  # one step at a time against one batch: float rounding apart
        torch.testing.assert_close(nxt[name].squeeze(-1), expected[name], rtol=1e-4, atol=1e-4)
    score = nxt["ood_score"].squeeze(-1)
    torch.testing.assert_close(nxt["ood_window"].squeeze(-1), running_mean(score, 5, trajectory).float())
    assert torch.equal(nxt["ood_alarm"].squeeze(-1), nxt["ood_window"].squeeze(-1) > monitor.window_threshold)
    assert torch.equal(nxt["ood"].squeeze(-1), score > monitor.threshold)
    step_in_episode = torch.arange(40) - torch.cummax(torch.where(
        torch.cat([torch.ones(1, dtype=torch.bool), trajectory[1:] != trajectory[:-1]]), torch.arange(40), 0), 0).values
    assert torch.equal(nxt["ood_count"].squeeze(-1), (step_in_episode + 1).clamp_max(5))
    # the reset row carries zeros, an empty window and no alarm
    assert (rollout["ood_window"][0] == 0).all() and not rollout["ood_alarm"][0].any()
    assert rollout["ood_count"][0].item() == 0


def test_env_with_a_monitor_for_another_env_is_refused():
    other = DeploymentMonitor(tsidm=small_tsidm(observation_dim=17), flag=False)
    with pytest.raises(MonitorError, match=r"size 17.*another environment"):
        TransformedEnv(GymEnv("Hopper-v4"), other).observation_spec
    other = DeploymentMonitor(tsidm=small_tsidm(action_dim=2), flag=False)
    with pytest.raises(MonitorError, match=r"actions of size 2"):
        TransformedEnv(GymEnv("Hopper-v4"), other).action_spec


def test_uncalibrated_flag_is_refused_and_flag_false_records_scores():
    env = TransformedEnv(GymEnv("Hopper-v4"), DeploymentMonitor(tsidm=small_tsidm()))
    with pytest.raises(MonitorError, match="not calibrated"):
        env.rollout(3)
    with pytest.raises(MonitorError, match="not calibrated"):
        DeploymentMonitor(tsidm=small_tsidm())(linear_plant(1))
    env = TransformedEnv(GymEnv("Hopper-v4"), DeploymentMonitor(tsidm=small_tsidm(), flag=False))
    rollout = env.rollout(3)
    assert "ood" not in rollout["next"].keys() and rollout["next", "ood_window"].shape == (3, 1)


@pytest.mark.parametrize("invert", [False, True])
def test_replay_buffer_sample_and_write_time(invert):
    monitor = small_monitor()
    data = linear_plant(2)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=16)
    rb.append_transform(monitor, invert=invert)
    rb.extend(data.clone())
    sample = rb.sample()
    expected = monitor.scores(sample["observation"], sample["action"], sample["next", "observation"])
    torch.testing.assert_close(sample["next", "ood_score"].squeeze(-1), expected["ood_score"])


# ------------------------------------------------------------------- files
def test_save_load_round_trip_with_weights_only(tmp_path):
    monitor = small_monitor(tsidm=small_tsidm())
    monitor.save(tmp_path / "monitor.pt", metadata={"dataset": "x"})
    torch.load(tmp_path / "monitor.pt", weights_only=True)  # a plain-tensor file
    loaded = DeploymentMonitor.load(tmp_path / "monitor.pt", observation_dim=OBS_DIM, action_dim=ACTION_DIM)
    data = linear_plant(2, seed=3)
    ours, theirs = monitor(data.clone())["next"], loaded(data.clone())["next"]
    for key in (*SCORE_TERMS, "ood_score", "ood"):
        torch.testing.assert_close(ours[key], theirs[key], rtol=0, atol=0)
    assert loaded.window_threshold == monitor.window_threshold and loaded.metadata["dataset"] == "x"
    assert loaded.combine == monitor.combine and loaded.terms == monitor.terms


def test_loading_refuses_another_tasks_monitor_and_other_files(tmp_path):
    small_monitor(tsidm=small_tsidm()).save(tmp_path / "monitor.pt")
    with pytest.raises(CheckpointError, match="observation_dim=11.*observation_dim=17"):
        DeploymentMonitor.load(tmp_path / "monitor.pt", observation_dim=17)
    small_monitor().save(tmp_path / "detectors.pt")
    with pytest.raises(CheckpointError, match="disagree on action_dim"):
        DeploymentMonitor.load(tmp_path / "detectors.pt", action_dim=2)
    small_tsidm().save(tmp_path / "tsidm.pt")
    with pytest.raises(CheckpointError, match="torchrl_tels.monitor/v2"):
        DeploymentMonitor.load(tmp_path / "tsidm.pt")


# ---------------------------------------------------------------------- bad input
def test_bad_data_and_options_are_refused_with_one_error():
    monitor = small_monitor()
    data = linear_plant(1)[:32]
    data["next", "observation"][3, 2] = float("nan")
    data["next", "observation"][5, 0] = float("inf")
    with pytest.raises(MonitorError, match=r"next observation holds NaN or inf in 2 transition"):
        monitor(data)
    wrong = linear_plant(1)[:8].exclude("action").set("action", torch.zeros(8, 2))
    with pytest.raises(MonitorError, match=r"action has shape \(8, 2\).*size 3"):
        monitor(wrong)
    with pytest.raises(MonitorError, match=r"no 'next' entry"):
        monitor(TensorDict({"observation": torch.zeros(2, OBS_DIM), "action": torch.zeros(2, 3)}, [2]))
    with pytest.raises(MonitorError, match="at least one detector"):
        DeploymentMonitor()
    with pytest.raises(MonitorError, match="score must be 'combined' or one of"):
        DeploymentMonitor(tsidm=small_tsidm(), score="loss")
    with pytest.raises(MonitorError, match="score must be 'combined' or one of"):
        DeploymentMonitor(tsidm=small_tsidm(), combine=["nearest_state"])
    with pytest.raises(MonitorError, match="disagree on observation_dim"):
        DeploymentMonitor(tsidm=small_tsidm(), states=NearestStateDistance(torch.randn(10, 17)))
    with pytest.raises(MonitorError, match="no 'episode' entry"):
        monitor.calibrate(linear_plant(2).exclude("episode"))
    bad = linear_plant(4)
    bad["action"][7, 0] = math.nan
    with pytest.raises(MonitorError, match="train data's action holds NaN"):
        DeploymentMonitor.cross_fit(bad, folds=2, steps=1)
    with pytest.raises(MonitorError, match="3 trajectories, fewer than folds=5"):
        DeploymentMonitor.cross_fit(linear_plant(3), folds=5, steps=1)
    assert issubclass(MonitorError, TelsError) and issubclass(MonitorError, ValueError)


# ------------------------------------------------------- the recipe's final evaluation
def test_evaluate_records_the_monitor_along_the_episodes():
    from omegaconf import OmegaConf

    from torchrl_tels.data import load_dataset
    from torchrl_tels.envs import get_task, rollout_episodes
    from torchrl_tels.modules import make_guide_policy, make_tels_actor
    from torchrl_tels.trainer import evaluate

    tsidm = small_tsidm()
    env = GymEnv("Hopper-v4")
    actor = make_tels_actor(tsidm, make_guide_policy(LATENT_DIM, num_cells=(16,)), env.action_spec)
    cfg = OmegaConf.create({"seed": 0, "eval": {"episodes": 2, "max_steps": 30}})
    monitor = small_monitor(load_dataset("hopper-medium-v2-10k")[:3000], window=7)
    stats = {"latent_step_rms": 1.0, "data_action_std": 1.0}
    task = get_task("hopper-medium-v2-10k")
    record = evaluate(cfg, actor, env, task, 7, stats, monitor=monitor)["monitor"]
    assert "monitor" not in evaluate(cfg, actor, env, task, 7, stats)
    # the same seeded episodes, scored here
    episodes = list(rollout_episodes(actor, env, 2, seed=7, max_steps=30))
    expected = [monitor.scores(r["observation"], r["action"], r["next", "observation"])["ood_score"]
                for r in episodes]
    assert [len(s) for s in record["scores"]] == [len(e) for e in expected]
    for scores, windows, hand in zip(record["scores"], record["windows"], expected):
        torch.testing.assert_close(torch.tensor(scores), hand)
        torch.testing.assert_close(torch.tensor(windows), running_mean(hand, 7).float())
    flat = torch.cat(expected)
    assert record["ood_fraction"] == pytest.approx((flat > monitor.threshold).float().mean().item())
    alarms = torch.cat([running_mean(e, 7) for e in expected]) > monitor.window_threshold
    assert record["alarm_fraction"] == pytest.approx(alarms.float().mean().item())
    assert record["window_threshold"] == float(monitor.window_threshold) and record["quantile"] == 0.9


# ---------------------------------------------------------- the benchmark's helpers
def test_auroc_is_the_mann_whitney_statistic_on_a_hand_computed_case():
    from benchmarks.monitor_benchmark import auroc

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


def test_full_windows_lie_inside_one_trajectory():
    from benchmarks.monitor_benchmark import full_windows

    scores = torch.arange(8, dtype=torch.float64)
    trajectory = torch.tensor([0, 0, 0, 1, 1, 1, 1, 2])
    # windows of 2: steps 1, 2 of the first trajectory, 4, 5, 6 of the second; none in the third (1 step)
    torch.testing.assert_close(full_windows(scores, trajectory, 2), torch.tensor([0.5, 1.5, 3.5, 4.5, 5.5],
                                                                                 dtype=torch.float64))


def test_trajectory_split_keeps_whole_trajectories():
    episode = torch.repeat_interleave(torch.arange(20), torch.arange(1, 21))  # lengths 1..20, 210 rows
    data = TensorDict({"episode": episode, "row": torch.arange(len(episode))}, [len(episode)])
    train, held = split_trajectories(data, 0.8, seed=0)
    assert sorted(torch.cat([train["row"], held["row"]]).tolist()) == list(range(len(episode)))
    assert not set(train["episode"].tolist()) & set(held["episode"].tolist())
    assert 0.8 * len(episode) <= len(train) < 0.8 * len(episode) + 20


# ------------------------------------------------------------------ the recipe
@pytest.mark.parametrize("override, message", [
    ("monitor.calibration=conformal", "monitor.calibration must be one of"),
    ("monitor.folds=1", "monitor.folds must be an integer >= 2"),
    ("monitor.window=0", "monitor.window must be an integer >= 1"),
    ("monitor.quantile=1.0", r"monitor.quantile must lie in \(0, 1\)"),
    ("monitor.num_cells=[0]", "monitor.num_cells must be a list of positive integers"),
])
def test_bad_monitor_config_is_one_config_error(override, message):
    from benchmarks.harness import recipe_config
    from torchrl_tels.config import validate_config
    from torchrl_tels.errors import ConfigError

    validate_config(recipe_config([]))
    with pytest.raises(ConfigError, match=message):
        validate_config(recipe_config([override]))


def test_recipe_monitor_is_fitted_once_and_read_back_on_resume(tmp_path, monkeypatch):
    from benchmarks.harness import recipe_config
    from torchrl_tels.trainer import check_monitor_data, make_monitor

    cfg = recipe_config(["budget=smoke", "monitor.window=4"])
    data = linear_plant(6)
    before = torch.random.get_rng_state()
    monitor = make_monitor(cfg, data, tmp_path)
    assert torch.equal(torch.random.get_rng_state(), before)  # the run's RNG stream is untouched
    assert (tmp_path / "monitor.pt").is_file() and monitor.metadata["calibration"] == "cross_fit_2"
    assert monitor.window == 4 and monitor.dynamics.members == cfg.monitor.members
    real_cross_fit = DeploymentMonitor.cross_fit
    calls = []
    monkeypatch.setattr(DeploymentMonitor, "cross_fit",
                        classmethod(lambda cls, *a, **k: calls.append(1) or real_cross_fit(*a, **k)))

    again = make_monitor(recipe_config(["budget=smoke", "monitor.window=4", "resume=true"]), data, tmp_path)
    assert not calls and again.threshold == monitor.threshold and again.window_threshold == monitor.window_threshold
    make_monitor(recipe_config(["budget=smoke", "monitor.window=5", "resume=true"]), data, tmp_path)
    assert len(calls) == 1  # other monitor settings: refitted
    make_monitor(recipe_config(["budget=smoke", "monitor.window=5", "seed=3"]), data, tmp_path)
    assert len(calls) == 2  # a fresh run in a used folder: refitted, never the old file

    with pytest.raises(MonitorError, match="needs at least 2 trajectories, and the training data holds 1"):
        check_monitor_data(cfg, linear_plant(1))
    split = recipe_config(["budget=smoke", "monitor.calibration=split"])
    assert make_monitor(split, data, tmp_path / "split").metadata["calibration"] == "split"


def test_bad_options_are_refused_before_any_fit(tmp_path, monkeypatch):
    with pytest.raises(MonitorError, match=r"quantile must lie in \(0, 1\)"):
        conformal_threshold(torch.arange(5.0), 0.0)
    monitor = small_monitor()
    monitor.save(tmp_path / "monitor.pt")
    with pytest.raises(MonitorError, match=r"\['window'\] are part of the saved monitor"):
        DeploymentMonitor.load(tmp_path / "monitor.pt", window=7)
    payload = torch.load(tmp_path / "monitor.pt", weights_only=True)
    del payload["calibration"]["term_scale"]
    torch.save(payload, tmp_path / "damaged.pt")
    with pytest.raises(CheckpointError, match="damaged.*term_scale"):
        DeploymentMonitor.load(tmp_path / "damaged.pt")

    def no_fit(*args, **kwargs):
        raise AssertionError("fitted before the options were checked")

    monkeypatch.setattr(DeploymentMonitor, "fit_detectors", staticmethod(no_fit))
    data = linear_plant(4)
    with pytest.raises(MonitorError, match=r"window_quantile must lie in \(0, 1\)"):
        DeploymentMonitor.cross_fit(data, folds=2, window_quantile=1.0)
    with pytest.raises(MonitorError, match="window must be at least 1"):
        DeploymentMonitor.fit(data, data, window=0)
    with pytest.raises(MonitorError, match="no 'episode' entry"):
        DeploymentMonitor.fit(data, data.exclude("episode"))
    with pytest.raises(MonitorError, match="cannot refit a TS-IDM"):
        DeploymentMonitor.cross_fit(data, folds=2, tsidm=small_tsidm())


def test_batched_env_restarts_the_window_of_the_env_that_reset_only():
    from torchrl.envs import SerialEnv

    from torchrl_tels.data import load_dataset

    monitor = small_monitor(load_dataset("hopper-medium-v2-10k")[:3000], window=5)
    env = TransformedEnv(SerialEnv(2, lambda: GymEnv("Hopper-v4")), monitor)
    env.set_seed(0)
    rollout = env.rollout(40, break_when_any_done=False)  # (2, 40): the two hoppers fall at different steps
    env.close()  # here, not at a garbage collection in a later test: closing resets torch's thread count
    for b in range(2):
        nxt = rollout[b]["next"]
        done = nxt["done"].squeeze(-1)
        trajectory = torch.cat([torch.zeros(1, dtype=torch.long), done[:-1].long().cumsum(0)])
        start = torch.cat([torch.ones(1, dtype=torch.bool), trajectory[1:] != trajectory[:-1]])
        step = torch.arange(40) - torch.cummax(torch.where(start, torch.arange(40), 0), 0).values
        assert torch.equal(nxt["ood_count"].squeeze(-1), (step + 1).clamp_max(5))
        score = nxt["ood_score"].squeeze(-1)
        torch.testing.assert_close(nxt["ood_window"].squeeze(-1), running_mean(score, 5, trajectory).float())
    ends = [rollout[b]["next", "done"].squeeze(-1)[:-1].nonzero().squeeze(-1).tolist() for b in range(2)]
    assert ends[0] and ends[1] and ends[0] != ends[1], ends  # the resets fall at different steps
