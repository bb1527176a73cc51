"""Adroit by D4RL name and Minari id: D4RL's reward, episode length, references and success, in the real envs."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_tels.collection import load_dapg_expert
from torchrl_tels.data import load_dataset
from torchrl_tels.envs import evaluate_episodes, get_task, make_eval_envs, normalized_score
from torchrl_tels.envs.adroit import ADROIT_TASKS, adroit_env_id

pytest.importorskip("gymnasium_robotics")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_ADROIT = REPO_ROOT.parent / "shared" / "datasets" / "adroit"
requires_shared = pytest.mark.skipif(not SHARED_ADROIT.is_dir(), reason=f"{SHARED_ADROIT} absent")

#: D4RL's infos.py reference returns (random, expert) and episode lengths, written out independently
D4RL = {"pen": (96.262799, 3076.8331017826877, 100), "door": (-56.512833, 2880.5693087298737, 200),
        "hammer": (-274.856578, 12794.134825156867, 200), "relocate": (-6.425911, 4233.877797728884, 200)}
SIZES = {"pen": (45, 24), "door": (39, 28), "hammer": (46, 26), "relocate": (39, 30)}


def palm_distance_from_observation(task: str, obs: np.ndarray) -> np.ndarray:
    """The palm-to-object distance read off the observation vector, as each env lays it out."""
    if task == "door":      # ..., palm - handle (3), door open flag
        return np.linalg.norm(obs[..., -4:-1], axis=-1)
    if task == "hammer":    # qpos[:-6] (27), qvel[-6:], palm (3), object (3), ...
        return np.linalg.norm(obs[..., 33:36] - obs[..., 36:39], axis=-1)
    if task == "relocate":  # qpos[:-6] (30), palm - object (3), ...
        return np.linalg.norm(obs[..., 30:33], axis=-1)
    return np.zeros(obs.shape[:-1])


@pytest.mark.parametrize("task", list(ADROIT_TASKS))
def test_names_resolve_to_d4rl_env_length_and_references(task):
    low, high, steps = D4RL[task]
    names = [f"{task}-{q}-v1" for q in ("human", "cloned", "expert")]
    names += [f"{task}-expert-v1-10k", *(f"D4RL/{task}/{q}-v2" for q in ("human", "cloned", "expert"))]
    for name in names:
        t = get_task(name)
        assert (t.env_id, t.ref_min_score, t.ref_max_score, t.max_episode_steps) == (adroit_env_id(task), low, high,
                                                                                     steps), name
        assert (t.observation_dim, t.action_dim) == SIZES[task] and t.info_keys == ("success",)
    env = gym.make(adroit_env_id(task))
    assert env.observation_space.shape == (SIZES[task][0],) and env.action_space.shape == (SIZES[task][1],)
    env.reset(seed=0)
    n, truncated = 0, False
    while not truncated:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        n += 1
        assert not terminated
    assert n == steps  # pen: 100, not the 200 the installed env registers


@pytest.mark.parametrize("task", ["door", "hammer", "relocate", "pen"])
def test_reward_is_d4rls_formula(task):
    """Stepped with a shipped trajectory's actions, the env's reward is v1's minus 0.2 * the palm distance
    read off the observation; and the shipped rewards obey the same formula against their own v1 column."""
    name = {"door": "door-human-v1"}.get(task, f"{task}-expert-v1-10k")
    data = load_dataset(name)
    ours, raw = gym.make(adroit_env_id(task)), gym.make(ADROIT_TASKS[task].base_env_id)
    ours.reset(seed=3), raw.reset(seed=3)
    for action in data["action"][:60].numpy():
        obs, reward, *_ = ours.step(action)
        _, reward_v1, *_ = raw.step(action)
        expected = reward_v1 - (0.2 * palm_distance_from_observation(task, obs) if task != "pen" else 0.0)
        assert reward == pytest.approx(expected, abs=1e-6)
    if task != "pen":
        assert not np.allclose(reward, reward_v1)  # the v1 sign is undone, not copied
    if SHARED_ADROIT.is_dir():
        file = {"door-human-v1": "door-human"}.get(name, name.replace("-v1", ""))
        with np.load(SHARED_ADROIT / f"{file}.npz") as raw_data:
            distance = palm_distance_from_observation(task, raw_data["next_observations"])
            expected = raw_data["rewards_v1"] - (0.2 * distance if task != "pen" else 0.0)
            np.testing.assert_allclose(raw_data["rewards"], expected, atol=1e-5)
            np.testing.assert_allclose(data["next", "reward"].numpy()[:, 0], raw_data["rewards"])


def dapg_expert(task: str):
    return load_dapg_expert(SHARED_ADROIT / "policies" / f"{task}-v0-dapg-policy.npz")


@requires_shared
@pytest.mark.parametrize("task", ["door", "hammer"])
def test_dapg_expert_scores_about_100_and_succeeds(task):
    """D4RL's reference 'expert' is the DAPG expert: through these envs and references it must score about 100
    (the data README measured door 105.1, hammer 128.5 over 10 episodes) and succeed by D4RL's criterion."""
    t = get_task(f"{task}-expert-v1")
    env = make_eval_envs(t.env_id, 3, info_keys=t.info_keys)
    episodes = evaluate_episodes(dapg_expert(task), env, 3, seed=0, max_steps=1000, success_steps=t.success_steps)
    scores = [normalized_score(t, e["return"]) for e in episodes]
    assert [e["length"] for e in episodes] == [200] * 3
    assert all(e["success"] for e in episodes)
    assert 95 < np.mean(scores) < 140, scores
    # A policy that does nothing neither succeeds nor scores near the expert.
    idle = TensorDictModule(lambda obs: torch.zeros(obs.shape[:-1] + (SIZES[task][1],)), in_keys=["observation"],
                            out_keys=["action"])
    still = evaluate_episodes(idle, env, 3, seed=0, success_steps=t.success_steps)
    assert not any(e["success"] for e in still)
    assert max(normalized_score(t, e["return"]) for e in still) < 20


def test_minari_adroit_id_loads_from_a_dataset_recorded_in_the_real_env(tmp_path, monkeypatch):
    import minari

    from torchrl_tels.collection import collect_minari_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset_id = "D4RL/door/expert-v2"
    collect_minari_dataset("AdroitHandDoor-v1", dataset_id, n_steps=30, seed=1)
    assert dataset_id in minari.list_local_datasets()
    data = load_dataset(dataset_id, download=False)
    task = get_task(dataset_id)
    assert data.shape == (30,)
    assert (data["observation"].shape[-1], data["action"].shape[-1]) == (task.observation_dim, task.action_dim)
    recorded = minari.load_dataset(dataset_id)
    episode = next(recorded.iterate_episodes())
    np.testing.assert_allclose(data["observation"].numpy(), episode.observations[:-1], rtol=1e-6)
    np.testing.assert_allclose(data["next", "reward"].numpy()[:, 0], episode.rewards, rtol=1e-6)
    env = make_eval_envs(task.env_id, 1, info_keys=task.info_keys)
    step = env.rand_step(env.reset())
    assert ("next", "success") in step.keys(True)


def test_recipe_smoke_run_on_door_human(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(REPO_ROOT / "recipes" / "tels_offline.py"), "domain=adroit", "budget=smoke",
           "dataset.name=door-human-v1", "threads=1", "tsidm.steps=30", "policy.steps=40", "eval.interval=20",
           "eval.episodes=2", "monitor.steps=10", f"run_dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "TORCHRL_TELS_SHARED_DATASETS": "/nonexistent"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((run_dir / "results.json").read_text())
    assert results["env"] == adroit_env_id("door")
    assert math.isfinite(results["final_normalized_score_mean"])
    last = results["evaluations"][-1]
    assert last["lengths"] == [200, 200]  # D4RL's door episodes
    assert 0.0 <= results["final_success_rate_mean"] <= 1.0 and "success_rate" in last


@requires_shared
def test_dapg_policy_is_the_readme_formula():
    arrays = dict(np.load(SHARED_ADROIT / "policies" / "door-v0-dapg-policy.npz"))
    obs = np.random.default_rng(0).normal(size=(5, 39)).astype(np.float32)
    x = (obs - arrays["in_shift"]) / (arrays["in_scale"] + 1e-8)
    h = np.tanh(np.tanh(x @ arrays["W0"].T + arrays["b0"]) @ arrays["W1"].T + arrays["b1"])
    expected = np.clip((h @ arrays["W2"].T + arrays["b2"]) * arrays["out_scale"] + arrays["out_shift"], -1, 1)
    out = dapg_expert("door")(TensorDict(observation=torch.as_tensor(obs), batch_size=[5]))["action"]
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-5, atol=1e-5)
