"""``study.realization``: rollout readings of a finished run, checked against the library's
own diagnostics, and the table they give."""
from __future__ import annotations

import json
import statistics

import pytest
import torch
import yaml

from study import proposal_cap, realization
from tests.test_export import make_run
from torchrl_tels.diagnostics import rollout_statistics
from torchrl_tels.envs import rollout_episodes


@pytest.fixture
def finished_run(tmp_path, monkeypatch):
    run_dir = make_run(tmp_path / "run")
    (run_dir / "results.json").write_text(json.dumps(
        {"task": "hopper-medium-v2-10k", "dataset": "hopper-medium-v2-10k", "seed": 3,
         "final_normalized_score_mean": 1.5}))
    (run_dir / "config.yaml").write_text(yaml.safe_dump({"seed": 3, "dataset": {"name": "hopper-medium-v2-10k"}}))
    monkeypatch.setattr(proposal_cap, "EPISODES", 2)
    monkeypatch.setattr(realization, "EPISODES", 2)
    return run_dir


def test_a_reading_averages_the_rollout_statistics_of_its_episodes(finished_run):
    record = realization.realization(finished_run)
    run = proposal_cap.load_finished_run(finished_run, episodes=2)
    episodes = list(rollout_episodes(run.actor, run.env, 2, seed=3 * 100_000 + 1))
    assert record["lengths"] == [e.shape[-1] for e in episodes]
    for key in realization.ROLLOUT_KEYS:
        expected = statistics.mean(rollout_statistics(e)[key] for e in episodes)
        assert record["rollouts"][key] == pytest.approx(expected, rel=1e-5), key
    opening = statistics.mean(rollout_statistics(e[:realization.OPENING_STEPS])["realized_error_ratio"]
                              for e in episodes)
    assert record["rollouts"]["opening_realized_error_ratio"] == pytest.approx(opening, rel=1e-5)
    assert record["final_score"] == 1.5 and len(record["returns"]) == 2
    # an untrained guide predicts the data's next latent no better than by chance
    assert record["on_data"]["guide_error_ratio"] > 0.5
    step = record["one_step_from_data"]
    assert step["states"] == realization.ONE_STEP_STATES
    # the simulator replays the data's own actions far closer to the data's next states than an untrained
    # guide's actions reach its proposals
    assert step["data_action"]["median"] < 0.1 < step["actor"]["median"]
    assert all(-1 <= v <= 1 for v in step["rank_correlation"].values())


def test_the_simulator_restarted_from_an_observation_takes_the_same_step():
    import gymnasium as gym
    import numpy as np

    recorded, replayed = gym.make("Hopper-v4"), gym.make("Hopper-v4")
    observation, _ = recorded.reset(seed=0)
    action = np.array([0.3, -0.5, 0.8])
    for _ in range(5):  # away from the initial pose, moving (and below the observation's velocity clip, 10)
        observation = recorded.step(action)[0]
    expected = recorded.step(-action)[0]
    replayed.reset(seed=7)
    got = realization.one_step(replayed, torch.as_tensor(observation[None]), torch.as_tensor(-action[None]))
    np.testing.assert_allclose(got[0].numpy(), expected, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="qpos"):
        realization.set_state_from_observation(replayed, observation[:-1])


def test_table_rows_follow_arm_task_and_seed():
    record = {"score": 40.0, "lengths": [100, 300], "data_step_rms": 2.0,
              "on_data": {"guide_error_ratio": 0.25},
              "rollouts": {"guide_step_rms": 1.0, "realized_error_ratio": 0.5, "opening_realized_error_ratio": 0.4,
                           "realized_step_cosine": 0.75},
              "one_step_from_data": {**{k: {"median": 0.1, "rms": 0.2} for k in
                                        ("data_action", "inverse_action", "actor", "model_data", "model_actor")},
                                     "rank_correlation": {"model_miss": 0.8, "tsym": 0.3}}}
    text = realization.table({("b", "t", 1): record, ("a", "t", 2): record, ("a", "t", 0): record})
    rows = text.split("\n\n")[0].splitlines()[2:]
    assert [r.split(" | ")[:3] for r in rows] == [["| a", "t", "0"], ["| a", "t", "2"], ["| b", "t", "1"]]
    assert rows[0].endswith("| 40.0 | 200 | 0.25 | 0.50 | 0.50 | 0.40 | 0.75 |")
    step_rows = text.split("\n\n")[1].splitlines()[2:]
    assert len(step_rows) == 3 and step_rows[0].endswith("| 40.0 " + "| 0.10 (0.20) " * 5 + "| 0.80, 0.30 |")


def test_a_folder_that_is_not_a_finished_run_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        realization.main(["--run-dir", str(tmp_path), "--name", "x-hopper-medium-v2-10k-seed0"])
    assert "is missing: pass a finished run folder" in capsys.readouterr().err
    assert not realization.RESULTS.joinpath("x-hopper-medium-v2-10k-seed0.json").exists()
