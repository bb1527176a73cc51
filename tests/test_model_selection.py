"""``study.model_selection``: the per-state rank correlation against the textbook formula,
the candidates and the choice against a loop over the TS-IDM's maps by hand, and the own-candidate policy
against the run's actor, action for action and score for score."""
from __future__ import annotations

import pytest
import scipy.stats
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from study import model_selection
from study.proposal_cap import load_finished_run
from torchrl_tels.envs import evaluate_policy, normalized_score
from torchrl_tels.modules import make_tels_actor


def _textbook_spearman(x: list[float], y: list[float]) -> float:
    """1 − 6 Σ d² / (n (n² − 1)), ranks by sorting (no ties)."""
    n = len(x)
    rank = lambda v: {i: r for r, i in enumerate(sorted(range(n), key=v.__getitem__))}
    rx, ry = rank(x), rank(y)
    return 1 - 6 * sum((rx[i] - ry[i]) ** 2 for i in range(n)) / (n * (n * n - 1))


def test_row_spearman_matches_the_textbook_formula_row_by_row():
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(6, 16, generator=generator)
    y = x + torch.randn(6, 16, generator=generator) * torch.linspace(0.1, 5, 6).unsqueeze(-1)
    got = model_selection.row_spearman(x, y)
    expected = torch.tensor([_textbook_spearman(a.tolist(), b.tolist()) for a, b in zip(x, y)], dtype=got.dtype)
    torch.testing.assert_close(got, expected)
    assert got[0] > 0.9 and torch.isnan(model_selection.row_spearman(x, torch.ones(6, 16))).all()


def test_row_spearman_gives_tied_values_their_mean_rank():
    generator = torch.Generator().manual_seed(1)
    x = torch.randn(5, 16, generator=generator)
    y = torch.where(x < 0, 0.0, x + torch.randn(5, 16, generator=generator))  # ties: the candidates that fell
    got = model_selection.row_spearman(x, y)
    expected = torch.tensor([scipy.stats.spearmanr(a, b).statistic for a, b in zip(x.numpy(), y.numpy())])
    torch.testing.assert_close(got, expected.to(got.dtype))


@pytest.fixture
def finished_run(finished_recipe_run):
    torch.set_num_threads(1)
    return load_finished_run(finished_recipe_run, episodes=2)


def _choice(run, choose, reencode_proposal=False, seed=0):
    actor = make_tels_actor(run.tsidm, run.actor[1], run.env.action_spec_unbatched,
                            reencode_proposal=reencode_proposal)
    sigma = torch.full((run.data["action"].shape[-1],), 0.3)
    return actor, model_selection.LatentActionChoice(run.tsidm, run.actor[1].module, actor[-1].module, sigma,
                                                     choose, seed=seed)


@pytest.mark.parametrize("reencode_proposal", [False, True])
def test_the_own_candidate_is_the_actors_action(finished_run, reencode_proposal):
    actor, choice = _choice(finished_run, model_selection.own_action, reencode_proposal)
    observation = finished_run.data["observation"][:40]
    with torch.no_grad():
        expected = actor(TensorDict({"observation": observation}, [40]))["action"]
    torch.testing.assert_close(choice(observation), expected)


def test_candidates_perturb_the_latent_action_by_sigma_and_predict_by_the_forward_model(finished_run):
    tsidm = finished_run.tsidm
    _, choice = _choice(finished_run, model_selection.own_action)
    observation = finished_run.data["observation"][:500]
    latent, latent_actions, predicted = choice.candidates(observation)
    assert latent_actions.shape == (model_selection.CANDIDATES, 500, latent_actions.shape[-1])
    noise = latent_actions[1:] - latent_actions[0]
    torch.testing.assert_close(noise.std((0, 1)), choice.sigma, rtol=0.05, atol=0)
    with torch.no_grad():
        for k in (0, 7):
            by_hand = latent + tsidm.forward_dynamics(latent, latent_actions[k])
            torch.testing.assert_close(predicted[k], by_hand)


def test_choosing_by_value_acts_the_candidate_of_largest_value_at_its_predicted_next_latent(finished_run):
    tsidm = finished_run.tsidm
    direction = torch.randn(tsidm.latent_state_dim, generator=torch.Generator().manual_seed(3))
    value = lambda latent: latent @ direction
    _, choice = _choice(finished_run, model_selection.by_value(value), seed=5)
    _, twin = _choice(finished_run, model_selection.own_action, seed=5)  # the same candidates
    observation = finished_run.data["observation"][:30]
    acted = choice(observation)
    _, latent_actions, predicted = twin.candidates(observation)
    expected = []
    for state in range(30):
        scores = [float(predicted[k, state] @ direction) for k in range(model_selection.CANDIDATES)]
        best = max(range(len(scores)), key=scores.__getitem__)
        expected.append(twin.actions(latent_actions[best, state]))
    torch.testing.assert_close(acted, torch.stack(expected))
    assert not torch.allclose(acted, twin.actions(latent_actions[0]))  # the choice is not the actor's own


def test_a_reading_of_a_recipe_run(finished_recipe_run, monkeypatch):
    monkeypatch.setattr(model_selection, "start_rows", lambda data: torch.arange(12))
    monkeypatch.setattr(model_selection, "HORIZON", 5)
    monkeypatch.setattr(model_selection, "EPISODES", 2)
    monkeypatch.setattr(model_selection, "LOCAL_STATES", 12)
    monkeypatch.setattr(model_selection, "NUDGE", 0.0)  # the repeat is then the same rollout
    record = model_selection.model_selection(finished_recipe_run)
    assert record["states"] == 12 and record["candidates"] == model_selection.CANDIDATES
    for key in ("model_rank", "tsym_rank"):
        assert -1.0 <= record[key]["median"] <= 1.0 and 0 < record[key]["rows"] <= 12
    # each candidate's first step, then the actor: the actor's own candidate's is the actor's rollout
    local = record["local"]
    assert local["states"] == 12 and local["actor_return"] == pytest.approx(record["horizon_return"]["actor"])
    assert all(-1.0 <= local[key] <= 1.0 for key in ("value_rank", "model_rank", "reward_rank",
                                                      "reward_and_value_rank"))
    assert local["return_spread"] > 0.0
    assert local["repeat_rank"] == pytest.approx(1.0)  # the simulator restarted from a state is deterministic
    # the best candidate is at least the chosen one, the actor's own (gain 0) included
    assert record["best"]["median"] >= max(record["chosen"]["median"], record["other"]["median"], 0.0)
    # acting through the candidates' own (k = 0) is the run's actor: its score, episode for episode
    run = load_finished_run(finished_recipe_run, episodes=2)
    returns = evaluate_policy(run.actor, run.env, 2, seed=run.seed)
    expected = float(normalized_score(run.task, torch.tensor(returns)).mean())
    assert record["episodes"]["scores"]["actor"] == pytest.approx(expected, rel=1e-6)
    text = model_selection.table({("arm", "task", 0): record})
    assert text.splitlines()[2].startswith("| arm | task | 0 | ")


def test_a_reading_at_its_own_horizon_reads_every_return_over_it(finished_recipe_run, monkeypatch):
    monkeypatch.setattr(model_selection, "start_rows", lambda data: torch.arange(6))
    monkeypatch.setattr(model_selection, "HORIZON", 5)
    monkeypatch.setattr(model_selection, "EPISODES", 1)
    monkeypatch.setattr(model_selection, "LOCAL_STATES", 6)
    short, default = (model_selection.model_selection(finished_recipe_run, horizon=h) for h in (2, None))
    assert (short["horizon"], default["horizon"]) == (2, 5)
    # the local returns after the actor's own candidate are the actor's rollouts over the same horizon
    for record in (short, default):
        assert record["local"]["actor_return"] == pytest.approx(record["horizon_return"]["actor"])
    assert short["horizon_return"]["actor"] < default["horizon_return"]["actor"]  # rewards are positive here


def test_a_local_q_reading_reads_model_selections_candidates_and_returns(finished_recipe_run, monkeypatch):
    from study import local_q

    monkeypatch.setattr(model_selection, "LOCAL_STATES", 12)  # local_q reads its states through model_selection
    monkeypatch.setattr(model_selection, "start_rows", lambda data: torch.arange(12))
    monkeypatch.setattr(model_selection, "HORIZON", 5)
    monkeypatch.setattr(model_selection, "EPISODES", 2)
    monkeypatch.setattr(local_q, "EPISODES", 2)
    monkeypatch.setattr(local_q, "IQL_STEPS", 30)
    monkeypatch.setattr(local_q, "RETURN_Q_STEPS", 30)
    record = local_q.local_q(finished_recipe_run, horizon=4)
    reference = model_selection.model_selection(finished_recipe_run, horizon=4)
    # the same states, candidates and continuation: the actor's own candidate's returns agree
    assert record["actor_return"] == pytest.approx(reference["local"]["actor_return"])
    assert record["states"] == 12 and -1.0 <= record["q_rank"] <= 1.0 and record["iql_steps"] == 30
    assert record["horizon"] == 4
    fitted = record["return_q"]
    assert -1.0 <= fitted["rank"] <= 1.0 and fitted["held_out_rows"] > 0 and fitted["steps"] == 30
    # the return Q fits, or holds out, exactly the training rows that record their 4-step return
    from study.value_delivery import known_returns, run_config
    from torchrl_tels.trainer import make_data
    data, _ = make_data(run_config(finished_recipe_run))
    assert fitted["rows"] + fitted["held_out_rows"] == int(known_returns(data, 4).sum())
    assert local_q.table({("arm", "task", 0): record}).splitlines()[2].startswith("| arm | task | 0 | ")


def test_min_q_is_the_smaller_of_iqls_two_critics():
    from benchmarks.baselines import HYPERPARAMETERS, _build_iql
    from study.local_q import min_q
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(3), torch.ones(3), shape=(3,))
    _, _, loss = _build_iql("observation", 5, spec, HYPERPARAMETERS["iql"])
    observation, action = torch.randn(7, 5), torch.rand(7, 3) * 2 - 1
    critics = []
    for k in range(2):
        net = loss.qvalue_network
        with loss.qvalue_network_params[k].to_module(net):
            critics.append(net(TensorDict({"observation": observation, "action": action}, [7]))["state_action_value"])
    expected = torch.minimum(*critics).squeeze(-1)
    assert not torch.allclose(critics[0], critics[1])  # two critics initialized apart: the minimum is a choice
    torch.testing.assert_close(min_q(loss, observation, action), expected)


def test_episode_changes_are_paired_per_seed():
    def record(actor, chosen, random):
        return {"episodes": {"scores": {"actor": actor, "chosen": chosen, "random": random}}}

    records = {("arm", "task", 0): record(10.0, 14.0, 9.0), ("arm", "task", 1): record(30.0, 28.0, 29.0),
               ("arm", "other", 0): record(5.0, 6.0, 7.0)}
    lines = model_selection.episode_changes(records)
    assert lines == [f"- arm, other, {model_selection.EPISODES} episodes against the actor's: chosen +1.0 (1 of 1 up); "
                     "random +2.0 (1 of 1 up).",
                     f"- arm, task, {model_selection.EPISODES} episodes against the actor's: chosen +1.0 (1 of 2 up); "
                     "random -1.0 (0 of 2 up)."]


def test_the_table_puts_each_local_rank_under_its_column():
    summary = {"median": 0.01, "share_positive": 0.5}
    local = {"value_rank": 0.11, "model_rank": 0.22, "reward_rank": 0.33, "reward_and_value_rank": 0.44,
             "repeat_rank": 0.98, "return_spread": 0.0123, "chosen_gain": summary}
    record = {"final_score": 40.0, "model_rank": {"median": 0.5}, "tsym_rank": {"median": 0.0},
              "predicted": summary, "chosen": summary, "best": summary, "other": summary, "local": local,
              "horizon_return": {"actor": 1.0, "chosen": 2.0, "random": 3.0, "chosen_over_actor": 0.5},
              "episodes": {"scores": {"actor": 1.0, "chosen": 2.0, "random": 3.0}}}
    header, rule, row = model_selection.table({("arm", "task", 0): record}).splitlines()[:3]
    cells = dict(zip(header.strip("| ").split(" | "), row.strip("| ").split(" | ")))
    assert len(cells) == rule.count("---") == row.count(" | ") + 1
    assert cells["local: rank with the return after of V, model, reward, r + γV; nudged repeat"] == \
        "0.11, 0.22, 0.33, 0.44; 0.98"
    assert cells["local: return spread over V's spread"] == "0.012"
