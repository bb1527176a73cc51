"""load_dataset on Minari datasets created locally (no network)."""

from __future__ import annotations

import gymnasium as gym
import minari
import numpy as np
import pytest
import torch
from minari.data_collector.episode_buffer import EpisodeBuffer

import torchrl_tels.data.datasets as datasets_module
from torchrl_tels.data import DatasetError, load_dataset

MAZE_ID = "test/pointmaze/toy-v0"
OBS_SPACE = gym.spaces.Dict(
    {
        "observation": gym.spaces.Box(-10, 10, (4,), np.float64),
        "achieved_goal": gym.spaces.Box(-10, 10, (2,), np.float64),
        "desired_goal": gym.spaces.Box(-10, 10, (2,), np.float64),
    }
)
ACTION_SPACE = gym.spaces.Box(-1, 1, (2,), np.float32)


def make_episode(
    episode_id: int, num_steps: int, rng, *, terminated=False, truncated=False
):
    observations = {
        key: rng.normal(size=(num_steps + 1, *space.shape))
        for key, space in OBS_SPACE.items()
    }
    terminations = np.zeros(num_steps, dtype=bool)
    truncations = np.zeros(num_steps, dtype=bool)
    terminations[-1] = terminated
    truncations[-1] = truncated
    return EpisodeBuffer(
        id=episode_id,
        observations=observations,
        actions=rng.uniform(-1, 1, size=(num_steps, 2)).astype(np.float32),
        rewards=rng.normal(size=num_steps),
        terminations=terminations,
        truncations=truncations,
        infos={},
    )


@pytest.fixture
def maze_dataset(tmp_path, monkeypatch):
    """A 3-episode dict-observation Minari dataset in a temporary root."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    rng = np.random.default_rng(0)
    episodes = [
        make_episode(0, 5, rng, terminated=True),
        make_episode(1, 4, rng, truncated=True),
        make_episode(2, 3, rng),  # recording cut short: neither flag
    ]
    minari.create_dataset_from_buffers(
        MAZE_ID,
        episodes,
        observation_space=OBS_SPACE,
        action_space=ACTION_SPACE,
        algorithm_name="test",
        author="test",
        author_email="test@example.com",
        code_permalink="none",
        description="toy maze",
        eval_env=None,
    )
    return episodes


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_minari_dict_observations_flattened(maze_dataset):
    data = load_dataset(MAZE_ID)
    assert data.batch_size == torch.Size([12])
    assert data["observation"].dtype == torch.float32
    assert data["observation"].shape == (12, 8)

    row = 0
    for episode_id, episode in enumerate(maze_dataset):
        # Default order: the Dict space's (sorted) key order.
        flat = np.concatenate(
            [
                episode.observations[key]
                for key in ("achieved_goal", "desired_goal", "observation")
            ],
            axis=1,
        ).astype(np.float32)
        steps = len(episode.rewards)
        rows = slice(row, row + steps)
        np.testing.assert_array_equal(data["observation"][rows].numpy(), flat[:-1])
        np.testing.assert_array_equal(
            data["next", "observation"][rows].numpy(), flat[1:]
        )
        np.testing.assert_array_equal(data["action"][rows].numpy(), episode.actions)
        np.testing.assert_array_equal(
            data["next", "reward"][rows, 0].numpy(), episode.rewards.astype(np.float32)
        )
        np.testing.assert_array_equal(
            data["desired_goal"][rows].numpy(),
            episode.observations["desired_goal"][:-1].astype(np.float32),
        )
        np.testing.assert_array_equal(
            data["next", "desired_goal"][rows].numpy(),
            episode.observations["desired_goal"][1:].astype(np.float32),
        )
        assert data["episode"][rows].tolist() == [episode_id] * steps
        row += steps

    ends = np.cumsum([5, 4, 3]) - 1
    assert data["next", "done"][:, 0].nonzero().squeeze(-1).tolist() == ends.tolist()
    assert data["next", "terminated"][:, 0].nonzero().squeeze(-1).tolist() == [4]
    # Episode 1 is truncated; episode 2 has no flag and is marked truncated.
    assert data["next", "truncated"][:, 0].nonzero().squeeze(-1).tolist() == [8, 11]


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_minari_observation_keys_and_goal_key(maze_dataset):
    data = load_dataset(
        MAZE_ID, observation_keys=["observation", "desired_goal"], goal_key=None
    )
    first = maze_dataset[0].observations
    expected = np.concatenate([first["observation"], first["desired_goal"]], axis=1)
    np.testing.assert_array_equal(
        data["observation"][:5].numpy(), expected[:-1].astype(np.float32)
    )
    assert "desired_goal" not in data.keys()

    with pytest.raises(
        DatasetError, match=r"observation key\(s\) \['velocity'\] not in"
    ):
        load_dataset(MAZE_ID, observation_keys=["velocity"])


def test_minari_missing_without_download(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(DatasetError) as info:
        load_dataset("mujoco/hopper/medium-v0", download=False)
    message = str(info.value)
    assert "Unknown dataset 'mujoco/hopper/medium-v0'" in message
    assert str(tmp_path / "mujoco/hopper/medium-v0") in message
    assert "download disabled" in message
    assert "minari download" in message


def test_minari_missing_without_remote_support(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    monkeypatch.setattr(
        datasets_module, "_minari_remote_support", lambda: "no remote package"
    )
    with pytest.raises(DatasetError, match="No download attempted: no remote package"):
        load_dataset("D4RL/antmaze/umaze-v1")


def test_minari_remote_support_check(monkeypatch):
    monkeypatch.setenv("MINARI_REMOTE", "ftp://somewhere")
    assert (
        "unknown MINARI_REMOTE scheme 'ftp'" in datasets_module._minari_remote_support()
    )
    monkeypatch.setenv("MINARI_REMOTE", "hf://farama-minari")
    monkeypatch.setattr(datasets_module.importlib.util, "find_spec", lambda name: None)
    assert 'pip install "minari[hf]"' in datasets_module._minari_remote_support()


def test_minari_download_failure_is_reported(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    monkeypatch.setattr(datasets_module, "_minari_remote_support", lambda: None)

    def no_network(dataset_id):
        raise ConnectionError("network unreachable")

    monkeypatch.setattr(minari, "download_dataset", no_network)
    with pytest.raises(
        DatasetError, match="Downloading it with Minari failed: network unreachable"
    ):
        load_dataset("mujoco/hopper/medium-v0")


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_minari_download_then_load(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    monkeypatch.setattr(datasets_module, "_minari_remote_support", lambda: None)
    rng = np.random.default_rng(1)
    episode = make_episode(0, 6, rng, truncated=True)
    requested = []

    def fake_download(dataset_id):
        # Stands in for the remote: writes the dataset where Minari would.
        requested.append(dataset_id)
        minari.create_dataset_from_buffers(
            dataset_id,
            [episode],
            observation_space=OBS_SPACE,
            action_space=ACTION_SPACE,
        )

    monkeypatch.setattr(minari, "download_dataset", fake_download)
    data = load_dataset("remote/maze/toy-v0", observation_keys=["observation"])
    assert requested == ["remote/maze/toy-v0"]
    np.testing.assert_array_equal(
        data["next", "observation"].numpy(),
        episode.observations["observation"][1:].astype(np.float32),
    )
