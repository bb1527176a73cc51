"""Tests of torchrl_tels.data: loading, validation, replay buffers, subsets."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ObservationNorm, RewardScaling

import torchrl_tels.data.datasets as datasets_module
from torchrl_tels.data import (
    EMBEDDED_DATASETS,
    PAPER_SUBSET_SIZES,
    DatasetError,
    embedded_dataset_path,
    delete_regions,
    load_dataset,
    make_offline_replay_buffer,
    points_in_boxes,
    shared_datasets_dir,
    subsample_transitions,
    subset_dataset,
    subset_trajectories,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_D4RL = REPO_ROOT.parent / "shared" / "datasets" / "d4rl-10k"
requires_shared = pytest.mark.skipif(
    not SHARED_D4RL.is_dir(),
    reason=f"shared D4RL subsets not found at {SHARED_D4RL} (../shared absent)",
)

# The paper's Table 1 sets, written out rather than read from EMBEDDED_DATASETS
# so that dropping one from the package fails here.
TABLE1_NAMES = [
    "hopper-medium-v2-10k",
    "hopper-medium-replay-v2-10k",
    "halfcheetah-medium-v2-10k",
    "walker2d-medium-v2-10k",
    "hopper-medium-expert-v2-10k",
    "walker2d-medium-replay-v2-10k",
    "walker2d-medium-expert-v2-10k",
    "halfcheetah-medium-replay-v2-10k",
    "halfcheetah-medium-expert-v2-10k",
    "antmaze-umaze-v0-10k",
    "antmaze-umaze-diverse-v0-10k",
]
#: the Adroit sets of Tables 1 and 6, shipped under their D4RL names; shared/datasets/adroit/ holds them as files
ADROIT_NAMES = {
    "door-human-v1": "door-human",
    "pen-expert-v1-10k": "pen-expert-10k",
    "door-expert-v1-10k": "door-expert-10k",
    "hammer-expert-v1-10k": "hammer-expert-10k",
    "relocate-expert-v1-10k": "relocate-expert-10k",
}
ASSETS = importlib.resources.files("torchrl_tels.data") / "assets"


def asset_arrays(name: str) -> dict[str, np.ndarray]:
    """The shipped file's arrays, read with NumPy alone (not through load_dataset)."""
    with importlib.resources.as_file(ASSETS / f"{name}.npz") as path, np.load(path) as raw:
        return {key: raw[key] for key in raw.files}


def make_arrays(num: int = 7, obs_dim: int = 3, act_dim: int = 2, seed: int = 0):
    """D4RL-style arrays of one continuous observation chain."""
    rng = np.random.default_rng(seed)
    chain = rng.normal(size=(num + 1, obs_dim)).astype(np.float32)
    return {
        "observations": chain[:-1].copy(),
        "next_observations": chain[1:].copy(),
        "actions": rng.uniform(-1, 1, size=(num, act_dim)).astype(np.float32),
        "rewards": rng.normal(size=num).astype(np.float32),
        "terminals": np.zeros(num, dtype=bool),
    }


def make_transitions(episode_lengths, obs_dim: int = 4) -> TensorDict:
    """Transitions of given trajectory lengths, with a ``row`` entry to trace rows."""
    num = int(sum(episode_lengths))
    episode = torch.repeat_interleave(
        torch.arange(len(episode_lengths)), torch.as_tensor(episode_lengths)
    )
    done = torch.zeros(num, 1, dtype=torch.bool)
    done[torch.as_tensor(episode_lengths).cumsum(0) - 1] = True
    observation = torch.randn(num, obs_dim, generator=torch.Generator().manual_seed(0))
    return TensorDict(
        {
            "observation": observation,
            "action": torch.zeros(num, 2),
            "episode": episode,
            "row": torch.arange(num),
            "next": {
                "observation": observation + 1,
                "reward": torch.zeros(num, 1),
                "terminated": done.clone(),
                "truncated": torch.zeros(num, 1, dtype=torch.bool),
                "done": done.clone(),
            },
        },
        batch_size=[num],
    )


def episode_lengths(data) -> list[int]:
    return torch.unique_consecutive(data["episode"], return_counts=True)[1].tolist()


# --------------------------------------------------------------------------- #
# Layout and values on the shipped D4RL subsets
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("name", TABLE1_NAMES)
def test_shipped_layout_and_values_match_file(name):
    raw = asset_arrays(name)
    data = load_dataset(name)
    num = len(raw["observations"])

    assert data.batch_size == torch.Size([num])
    expected_keys = {
        "observation",
        "action",
        "episode",
        ("next", "observation"),
        ("next", "reward"),
        ("next", "terminated"),
        ("next", "truncated"),
        ("next", "done"),
    }
    assert set(data.keys(True, True)) == expected_keys
    for key in ("observation", "action", ("next", "observation"), ("next", "reward")):
        assert data[key].dtype == torch.float32, key
    for key in ("terminated", "truncated", "done"):
        assert data["next", key].dtype == torch.bool
        assert data["next", key].shape == (num, 1)
    assert data["next", "reward"].shape == (num, 1)
    assert data["episode"].dtype == torch.int64 and data["episode"].shape == (num,)

    np.testing.assert_array_equal(data["observation"].numpy(), raw["observations"])
    np.testing.assert_array_equal(
        data["next", "observation"].numpy(), raw["next_observations"]
    )
    np.testing.assert_array_equal(data["action"].numpy(), raw["actions"])
    np.testing.assert_array_equal(data["next", "reward"].numpy()[:, 0], raw["rewards"])
    np.testing.assert_array_equal(
        data["next", "terminated"].numpy()[:, 0], raw["terminals"]
    )


@pytest.mark.parametrize(
    "name, num_episodes, num_terminated, num_truncated",
    [
        # README: 21 whole trajectories, each ending in a terminal.
        ("hopper-medium-v2-10k", 21, 21, 0),
        # 9 chunks of 998 steps, each followed by one step of the next episode.
        ("halfcheetah-medium-v2-10k", 18, 0, 18),
        ("walker2d-medium-v2-10k", 11, 3, 8),
        ("hopper-medium-replay-v2-10k", 50, 42, 8),
        ("antmaze-umaze-v0-10k", 105, 94, 11),
    ],
)
def test_shipped_episode_boundaries(name, num_episodes, num_terminated, num_truncated):
    raw = asset_arrays(name)
    data = load_dataset(name)
    episode = data["episode"]
    terminated = data["next", "terminated"][:, 0]
    truncated = data["next", "truncated"][:, 0]
    done = data["next", "done"][:, 0]

    assert int(episode.max()) + 1 == num_episodes
    assert int(terminated.sum()) == num_terminated
    assert int(truncated.sum()) == num_truncated
    # Ids start at 0 and go up by one exactly after each done.
    assert episode[0] == 0
    assert torch.equal(torch.diff(episode), done[:-1].long())
    assert torch.equal(done, terminated | truncated)
    assert not (terminated & truncated).any()
    assert done[-1]
    # Within an episode the observation chain is unbroken; every non-terminal
    # end is a real break of the chain (or the last row).
    continues = (raw["next_observations"][:-1] == raw["observations"][1:]).all(axis=1)
    assert continues[~done[:-1].numpy()].all()
    assert not continues[truncated[:-1].numpy()].any()

    if name == "hopper-medium-v2-10k":
        assert episode_lengths(data)[:3] == [334, 474, 330]
    if name == "halfcheetah-medium-v2-10k":
        assert episode_lengths(data) == [998, 1] * 9


def test_embedded_dataset_matches_asset():
    asset = importlib.resources.files("torchrl_tels.data") / "assets"
    assert (asset / "ATTRIBUTION.md").is_file()
    with importlib.resources.as_file(asset / "hopper-medium-v2-10k.npz") as path:
        raw = np.load(path)
        observations = raw["observations"]
    for name in ("hopper-medium-v2-10k", "embedded", "default"):
        data = load_dataset(name)
        np.testing.assert_array_equal(data["observation"].numpy(), observations)
        assert int(data["episode"].max()) + 1 == 21


def test_shipped_names_are_the_asset_files():
    shipped = sorted(p.name.removesuffix(".npz") for p in ASSETS.iterdir() if p.name.endswith(".npz"))
    assert shipped == sorted(EMBEDDED_DATASETS) == sorted([*TABLE1_NAMES, *ADROIT_NAMES])


@pytest.mark.parametrize("name", [*TABLE1_NAMES, *ADROIT_NAMES])
def test_shipped_name_loads_without_shared_folder(name, monkeypatch):
    # No shared folder anywhere, and fail loudly if load_dataset even asks for it.
    monkeypatch.setenv("TORCHRL_TELS_SHARED_DATASETS", "/nonexistent/shared/datasets")

    def no_shared():
        raise AssertionError("a shipped name must not consult the shared folder")

    monkeypatch.setattr(datasets_module, "shared_datasets_dir", no_shared)
    data = load_dataset(name)

    shared_file = (SHARED_D4RL.parent / "adroit" / f"{ADROIT_NAMES[name]}.npz" if name in ADROIT_NAMES
                   else SHARED_D4RL / f"{name}.npz")
    if not shared_file.is_file():
        pytest.skip(f"{shared_file} absent: loaded, but nothing to compare with")
    with np.load(shared_file) as raw:
        np.testing.assert_array_equal(data["observation"].numpy(), raw["observations"])
        np.testing.assert_array_equal(data["action"].numpy(), raw["actions"])
        np.testing.assert_array_equal(data["next", "observation"].numpy(), raw["next_observations"])
        np.testing.assert_array_equal(data["next", "reward"].numpy()[:, 0], raw["rewards"])
        np.testing.assert_array_equal(data["next", "terminated"].numpy()[:, 0], raw["terminals"])


def test_embedded_lookup_takes_only_shipped_names():
    for name in ("../assets/hopper-medium-v2-10k", "hopper-medium-v2", "ATTRIBUTION"):
        with pytest.raises(DatasetError, match="No embedded dataset named .*shipped: .*walker2d"):
            embedded_dataset_path(name)


def test_shipped_name_missing_from_install_is_an_error(tmp_path, monkeypatch):
    # An install without its package data says so rather than falling back to
    # ../shared (which holds a file of the same name here).
    monkeypatch.setattr(importlib.resources, "files", lambda package: tmp_path)
    with pytest.raises(DatasetError, match="'walker2d-medium-v2-10k' is missing from this installation"):
        load_dataset("walker2d-medium-v2-10k")


@requires_shared
def test_embedded_dataset_equals_shared_file():
    embedded = load_dataset("embedded")
    shared = load_dataset(SHARED_D4RL / "hopper-medium-v2-10k.npz")
    assert (embedded == shared).all()


@requires_shared
def test_shared_datasets_dir_default():
    assert shared_datasets_dir().resolve() == SHARED_D4RL.parent.resolve()  # ../shared may be a symlink


def test_shared_datasets_dir_override(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_TELS_SHARED_DATASETS", str(tmp_path))
    assert shared_datasets_dir() == tmp_path
    (tmp_path / "d4rl-10k").mkdir()
    arrays = make_arrays()
    np.savez(tmp_path / "d4rl-10k" / "toy-medium-v2-10k.npz", **arrays)
    data = load_dataset("toy-medium-v2-10k")
    np.testing.assert_array_equal(data["action"].numpy(), arrays["actions"])

    monkeypatch.setenv("TORCHRL_TELS_SHARED_DATASETS", str(tmp_path / "missing"))
    assert shared_datasets_dir() is None


# --------------------------------------------------------------------------- #
# Episode boundary recovery and file formats on small data
# --------------------------------------------------------------------------- #
def test_boundaries_from_terminals_timeouts_and_chain_breaks():
    arrays = make_arrays(num=7)
    arrays["terminals"][1] = True  # terminal end of episode 0
    arrays["timeouts"] = np.zeros(7, dtype=bool)
    arrays["timeouts"][3] = True  # time limit ends episode 1
    arrays["next_observations"][5] += 1.0  # chain break ends episode 2
    data = load_dataset(arrays)

    assert data["episode"].tolist() == [0, 0, 1, 1, 2, 2, 3]
    flags = data["next"]
    assert flags["terminated"][:, 0].tolist() == [0, 1, 0, 0, 0, 0, 0]
    assert flags["truncated"][:, 0].tolist() == [0, 0, 0, 1, 0, 1, 1]
    assert flags["done"][:, 0].tolist() == [0, 1, 0, 1, 0, 1, 1]


def test_terminal_and_timeout_on_same_step_is_terminated():
    arrays = make_arrays(num=3)
    arrays["terminals"][0] = True
    arrays["timeouts"] = np.array([True, False, False])
    data = load_dataset(arrays)
    assert data["next", "terminated"][0] and not data["next", "truncated"][0]


def test_npz_and_hdf5_files_load_the_same(tmp_path):
    arrays = make_arrays(num=5)
    # Other dtypes that cast cleanly: float64 values, 0/1 integer flags.
    arrays["observations"] = arrays["observations"].astype(np.float64)
    arrays["next_observations"] = arrays["next_observations"].astype(np.float64)
    arrays["terminals"] = np.array([0, 0, 1, 0, 0], dtype=np.int64)
    np.savez(tmp_path / "toy.npz", **arrays)
    with h5py.File(tmp_path / "toy.hdf5", "w") as file:
        for key, value in arrays.items():
            file[key] = value
        file["infos/qpos"] = np.zeros((5, 2))  # D4RL-style group: ignored

    from_npz = load_dataset(str(tmp_path / "toy.npz"))
    from_hdf5 = load_dataset(tmp_path / "toy.hdf5")
    assert (from_npz == from_hdf5).all()
    assert from_npz["observation"].dtype == torch.float32
    np.testing.assert_allclose(
        from_npz["observation"].numpy(), arrays["observations"], rtol=1e-6
    )
    assert from_npz["episode"].tolist() == [0, 0, 0, 1, 1]
    assert from_npz["next", "terminated"][:, 0].tolist() == [0, 0, 1, 0, 0]


def test_scalar_observations_and_column_rewards_are_reshaped():
    arrays = make_arrays(num=4, obs_dim=1)
    arrays["observations"] = arrays["observations"][:, 0]
    arrays["next_observations"] = arrays["next_observations"][:, 0]
    arrays["rewards"] = arrays["rewards"][:, None]
    data = load_dataset(arrays)
    assert data["observation"].shape == (4, 1)
    assert data["next", "reward"].shape == (4, 1)
    assert int(data["episode"].max()) == 0


# --------------------------------------------------------------------------- #
# Validation errors
# --------------------------------------------------------------------------- #
def _drop(key):
    def edit(arrays):
        del arrays[key]

    return edit


def _set(key, value_fn):
    def edit(arrays):
        arrays[key] = value_fn(arrays[key])

    return edit


def _nan(arrays):
    arrays["actions"][2, 1] = np.nan


def _inf(arrays):
    arrays["rewards"][4] = np.inf


@pytest.mark.parametrize(
    "edit, message",
    [
        (_drop("next_observations"), r"missing key\(s\) \['next_observations'\]"),
        (_drop("terminals"), r"missing key\(s\) \['terminals'\]"),
        (_set("rewards", lambda r: r[:-1]), "mismatched lengths"),
        (_nan, r"'actions' has 1 NaN/inf value\(s\) \(first at row 2\)"),
        (_inf, r"'rewards' has 1 NaN/inf value\(s\) \(first at row 4\)"),
        (
            _set("observations", lambda o: o.astype(np.float64) * 1e40),
            "'observations' .* NaN/inf",
        ),
        (
            _set("actions", lambda a: a.astype(str)),
            "'actions' has dtype <U.*cannot be cast",
        ),
        (_set("actions", lambda a: a.astype(object)), "'actions' has dtype object"),
        (_set("rewards", lambda r: r + 1j), "'rewards' has dtype complex"),
        (
            _set("terminals", lambda t: np.full(t.shape, 2)),
            "'terminals' must hold booleans or 0/1",
        ),
        (
            _set("rewards", lambda r: np.stack([r, r], 1)),
            r"'rewards' must have shape \(N,\)",
        ),
        (_set("next_observations", lambda o: o[:, :2]), "differ in shape"),
        (_set("rewards", lambda r: np.float32(1.0)), "'rewards' is a scalar"),
    ],
)
def test_validation_errors(edit, message):
    arrays = make_arrays(num=6)
    edit(arrays)
    with pytest.raises(DatasetError, match=message):
        load_dataset(arrays)


def test_empty_dataset_error():
    arrays = {key: value[:0] for key, value in make_arrays().items()}
    with pytest.raises(DatasetError, match=r"empty \(0 transitions\)"):
        load_dataset(arrays)


def test_dataset_error_is_value_error():
    assert issubclass(DatasetError, ValueError)


def test_missing_file_error(tmp_path):
    with pytest.raises(DatasetError, match="Dataset file not found: .*nothing.npz"):
        load_dataset(str(tmp_path / "nothing.npz"))
    with pytest.raises(DatasetError, match="Dataset file not found"):
        load_dataset("./relative/missing.hdf5")


def test_unreadable_files(tmp_path):
    (tmp_path / "notes.txt").write_text("not data")
    with pytest.raises(DatasetError, match="unsupported file type '.txt'"):
        load_dataset(tmp_path / "notes.txt")
    (tmp_path / "corrupt.npz").write_bytes(b"\x00garbage")
    with pytest.raises(DatasetError, match="could not be read"):
        load_dataset(tmp_path / "corrupt.npz")
    # Pickled object arrays are refused (allow_pickle=False).
    np.savez(tmp_path / "pickled.npz", observations=np.array([{"a": 1}], dtype=object))
    with pytest.raises(DatasetError, match="could not be read"):
        load_dataset(tmp_path / "pickled.npz")


def test_unknown_name_lists_what_was_looked_for(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(DatasetError) as info:
        load_dataset("no-such-dataset-v0", download=False)
    message = str(info.value)
    assert "Unknown dataset 'no-such-dataset-v0'" in message
    assert "embedded datasets" in message
    assert str(tmp_path / "no-such-dataset-v0") in message
    assert "download disabled" in message
    if SHARED_D4RL.is_dir():
        assert str(SHARED_D4RL / "no-such-dataset-v0.npz") in message


def test_unsupported_source_type():
    with pytest.raises(DatasetError, match="Unsupported dataset source of type int"):
        load_dataset(3)


# --------------------------------------------------------------------------- #
# Replay buffer
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def hopper():
    return load_dataset("hopper-medium-v2-10k")


def test_replay_buffer_holds_dataset_and_samples_rows(hopper):
    rb = make_offline_replay_buffer(hopper, 256, seed=0)
    assert len(rb) == len(hopper)
    stored = rb.storage[:]
    assert (stored.select(*hopper.keys()) == hopper).all()
    assert "index" not in hopper.keys()  # the caller's data is left alone

    batch = rb.sample()
    assert batch.batch_size == torch.Size([256])
    assert (batch.exclude("index") == hopper[batch["index"]]).all()


def test_replay_buffer_seed_is_reproducible(hopper):
    def indices(seed):
        rb = make_offline_replay_buffer(hopper, 64, seed=seed)
        return torch.cat([rb.sample()["index"] for _ in range(3)])

    torch.manual_seed(123)  # the global RNG must not matter
    first = indices(0)
    torch.manual_seed(456)
    assert torch.equal(first, indices(0))
    assert not torch.equal(first, indices(1))


def test_replay_buffer_without_replacement_covers_an_epoch(hopper):
    batch_size = 1000
    rb = make_offline_replay_buffer(
        hopper, batch_size, sampler="without_replacement", seed=0
    )
    batches = [rb.sample()["index"] for _ in range(len(hopper) // batch_size)]
    assert all(len(b) == batch_size for b in batches)
    seen = torch.cat(batches)
    assert len(seen.unique()) == len(seen) == 9000


def test_replay_buffer_write_and_read_transforms(hopper):
    loc = hopper["observation"].mean(0)
    scale = hopper["observation"].std(0)
    normalize = ObservationNorm(
        loc=-loc / scale,
        scale=1 / scale,
        in_keys=["observation", ("next", "observation")],
        standard_normal=False,
    )
    rb = make_offline_replay_buffer(
        hopper,
        128,
        write_transforms=normalize,
        transforms=RewardScaling(loc=0.0, scale=2.0, in_keys=[("next", "reward")]),
        seed=0,
    )
    expected_obs = (hopper["observation"] - loc) / scale
    # Encoded once at write time ...
    torch.testing.assert_close(rb.storage[:]["observation"], expected_obs)
    torch.testing.assert_close(
        rb.storage[:]["next", "reward"], hopper["next", "reward"]
    )
    # ... read transforms on every batch, write transforms not undone.
    batch = rb.sample()
    torch.testing.assert_close(batch["observation"], expected_obs[batch["index"]])
    torch.testing.assert_close(
        batch["next", "reward"], 2.0 * hopper["next", "reward"][batch["index"]]
    )
    torch.testing.assert_close(hopper["observation"], loc + scale * expected_obs)


def test_replay_buffer_prefetch(hopper):
    rb = make_offline_replay_buffer(hopper, 32, prefetch=2, seed=0)
    for _ in range(3):
        batch = rb.sample()
        assert (batch.exclude("index") == hopper[batch["index"]]).all()


@pytest.mark.parametrize("batch_size", [0, -1, 9014])
def test_replay_buffer_rejects_bad_batch_size(hopper, batch_size):
    with pytest.raises(ValueError, match=r"batch_size must be in \(0, 9013\]"):
        make_offline_replay_buffer(hopper, batch_size)


def test_replay_buffer_rejects_bad_inputs(hopper):
    with pytest.raises(ValueError, match="Unknown sampler 'prioritized'"):
        make_offline_replay_buffer(hopper, 8, sampler="prioritized")
    with pytest.raises(
        TypeError, match="must be a TensorDict of transitions, got dict"
    ):
        make_offline_replay_buffer({"observation": torch.zeros(4, 2)}, 2)
    with pytest.raises(TypeError, match=r"one batch dimension .* batch_size \(2, 2\)"):
        make_offline_replay_buffer(hopper[:4].reshape(2, 2), 2)


# --------------------------------------------------------------------------- #
# Reduced-size subsets
# --------------------------------------------------------------------------- #
def _whole_trajectories(subset, data) -> bool:
    """Every subset episode is one complete source trajectory."""
    ids, counts = torch.unique_consecutive(data["episode"], return_counts=True)
    source_lengths = dict(zip(ids.tolist(), counts.tolist(), strict=False))
    for episode_id in subset["episode"].unique():
        rows = subset["row"][subset["episode"] == episode_id]
        source = data["episode"][rows]
        if len(source.unique()) != 1:
            return False
        if not torch.equal(rows, torch.arange(rows[0], rows[0] + len(rows))):
            return False
        if len(rows) != source_lengths[int(source[0])]:
            return False
    return True


def test_subset_trajectories_whole_and_minimal():
    lengths = [30, 50, 20, 40, 60, 10, 25]
    data = make_transitions(lengths)
    subset = subset_trajectories(data, 100, seed=3)
    assert _whole_trajectories(subset, data)
    kept = episode_lengths(subset)
    # Reaches the target, and the last trajectory drawn (at most the longest
    # kept) was needed to get there.
    assert sum(kept) >= 100
    assert sum(kept) - max(kept) < 100
    assert (
        subset["episode"].tolist()
        == torch.repeat_interleave(torch.arange(len(kept)), torch.tensor(kept)).tolist()
    )
    assert subset["row"].tolist() == sorted(subset["row"].tolist())


def test_subset_trajectories_stops_at_first_reaching_draw():
    # Equal lengths make the count exact: ceil(100 / 30) = 4 trajectories.
    subset = subset_trajectories(make_transitions([30] * 8), 100, seed=5)
    assert episode_lengths(subset) == [30] * 4


def test_subset_dataset_dispatches_on_mode():
    data = make_transitions([30, 50, 20, 40, 60, 10, 25])
    by_trajectory = subset_dataset(data, 100, seed=3, mode="trajectories")
    assert torch.equal(by_trajectory["row"], subset_trajectories(data, 100, seed=3)["row"])
    by_transition = subset_dataset(data, 100, seed=3, mode="transitions")
    assert torch.equal(by_transition["row"], subsample_transitions(data, 100, seed=3)["row"])
    # Uniform rows cut trajectories; whole-trajectory draws do not.
    assert not _whole_trajectories(by_transition, data)
    with pytest.raises(ValueError, match="subset mode must be one of"):
        subset_dataset(data, 100, seed=3, mode="episodes")


def test_subset_trajectories_seeded():
    data = make_transitions([30, 50, 20, 40, 60, 10, 25, 35, 45])
    first = subset_trajectories(data, 120, seed=0)
    assert torch.equal(first["row"], subset_trajectories(data, 120, seed=0)["row"])
    others = [subset_trajectories(data, 120, seed=s)["row"] for s in range(1, 6)]
    assert any(not torch.equal(first["row"], other) for other in others)


def test_subset_trajectories_trim_cuts_last_drawn():
    data = make_transitions([30, 50, 20, 40, 60, 10, 25])
    whole = subset_trajectories(data, 100, seed=3)
    trimmed = subset_trajectories(data, 100, seed=3, trim=True)
    assert len(whole) == 110 and len(trimmed) == 100
    cut = sorted(set(whole["row"].tolist()) - set(trimmed["row"].tolist()))
    # Only the 10-row tail of one trajectory was cut ...
    assert len(cut) == 10 and cut == list(range(cut[0], cut[0] + 10))
    assert whole["next", "done"][whole["row"].tolist().index(cut[-1])]
    # ... and the row before it now ends its (truncated) trajectory.
    position = trimmed["row"].tolist().index(cut[0] - 1)
    assert trimmed["next", "truncated"][position]
    assert trimmed["next", "done"][position]
    assert not trimmed["next", "terminated"][position]
    assert int(trimmed["next", "done"].sum()) == int(trimmed["episode"].max()) + 1


@pytest.mark.parametrize("size", PAPER_SUBSET_SIZES)
def test_subset_trajectories_paper_sizes(size):
    data = make_transitions([1000] * 120, obs_dim=2)
    subset = subset_trajectories(data, size, seed=0)
    assert len(subset) == size  # whole 1000-step trajectories hit it exactly
    assert episode_lengths(subset) == [1000] * (size // 1000)
    assert len(subset_trajectories(data, size - 1, seed=0, trim=True)) == size - 1


def test_subset_trajectories_on_hopper(hopper):
    data = hopper.clone()
    data["row"] = torch.arange(len(data))
    subset = subset_trajectories(data, 5000, seed=0)
    assert _whole_trajectories(subset, data)
    assert 5000 <= len(subset) < 5000 + max(episode_lengths(data))
    assert int(subset["next", "terminated"].sum()) == int(subset["episode"].max()) + 1


def test_subsample_transitions():
    data = make_transitions([100] * 10)
    subset = subsample_transitions(data, 250, seed=7)
    assert len(subset) == 250
    rows = subset["row"]
    assert len(rows.unique()) == 250 and torch.equal(rows, rows.sort().values)
    assert (subset == data[rows]).all()
    assert torch.equal(rows, subsample_transitions(data, 250, seed=7)["row"])
    assert not torch.equal(rows, subsample_transitions(data, 250, seed=8)["row"])


@pytest.mark.parametrize("fn", [subset_trajectories, subsample_transitions])
@pytest.mark.parametrize("size", [0, 101])
def test_subset_size_errors(fn, size):
    with pytest.raises(ValueError, match=r"size must be in \(0, 100\]"):
        fn(make_transitions([50, 50]), size, seed=0)


def test_subset_trajectories_needs_episodes():
    data = make_transitions([5, 5]).exclude("episode")
    with pytest.raises(DatasetError, match="'episode'"):
        subset_trajectories(data, 5, seed=0)


# --------------------------------------------------------------------------- #
# Region deletion
# --------------------------------------------------------------------------- #
def grid_transitions() -> TensorDict:
    """Observations (x, y, z) on the integer grid [0, 9] x [0, 9], z = -x."""
    x, y = torch.meshgrid(torch.arange(10.0), torch.arange(10.0), indexing="ij")
    observation = torch.stack([x.flatten(), y.flatten(), -x.flatten()], dim=1)
    return TensorDict(
        {"observation": observation, "row": torch.arange(100)}, batch_size=[100]
    )


BOXES = [(1.0, 3.0, 2.0, 4.0), (6.5, 9.0, 0.0, 0.5)]


def test_delete_regions_ratio_one_removes_exactly_inside():
    data = grid_transitions()
    x, y = data["observation"][:, 0], data["observation"][:, 1]
    # By hand: box 1 holds x in {1,2,3}, y in {2,3,4} (bounds inclusive),
    # box 2 holds x in {7,8,9}, y = 0.
    inside = ((x >= 1) & (x <= 3) & (y >= 2) & (y <= 4)) | ((x >= 7) & (y == 0))
    assert int(inside.sum()) == 9 + 3
    assert torch.equal(points_in_boxes(data, BOXES), inside)

    kept = delete_regions(data, BOXES)
    assert kept["row"].tolist() == torch.arange(100)[~inside].tolist()


def test_delete_regions_partial_ratio():
    data = grid_transitions()
    inside = points_in_boxes(data, BOXES)
    kept = delete_regions(data, BOXES, ratio=0.5, seed=1)
    deleted = set(range(100)) - set(kept["row"].tolist())
    assert len(deleted) == 6  # round(0.5 * 12)
    assert deleted <= set(inside.nonzero().squeeze(-1).tolist())
    assert kept["row"].tolist() == sorted(kept["row"].tolist())
    again = delete_regions(data, BOXES, ratio=0.5, seed=1)
    assert torch.equal(kept["row"], again["row"])
    other_seeds = [
        delete_regions(data, BOXES, ratio=0.5, seed=s)["row"] for s in (2, 3, 4)
    ]
    assert any(not torch.equal(kept["row"], rows) for rows in other_seeds)
    assert len(delete_regions(data, BOXES, ratio=0.25, seed=0)) == 100 - 3
    assert len(delete_regions(data, BOXES, ratio=0.0)) == 100


def test_delete_regions_custom_columns():
    data = grid_transitions()
    # (x, y) taken as (y, -x): box over y in [0, 1], -x in [-2, 0] -> x in {0,1,2}.
    kept = delete_regions(data, [(0.0, 1.0, -2.0, 0.0)], xy_slice=[1, 2])
    assert len(kept) == 100 - 2 * 3
    assert not (
        (kept["observation"][:, 1] <= 1) & (kept["observation"][:, 0] <= 2)
    ).any()


def test_delete_regions_errors():
    data = grid_transitions()
    with pytest.raises(ValueError, match=r"ratio must be in \[0, 1\]"):
        delete_regions(data, BOXES, ratio=1.5)
    with pytest.raises(ValueError, match="is empty"):
        delete_regions(data, [(3.0, 1.0, 0.0, 1.0)])
    with pytest.raises(ValueError, match=r"A box is \(xmin, xmax, ymin, ymax\)"):
        delete_regions(data, [(0.0, 1.0, 0.0)])
    with pytest.raises(ValueError, match="must select exactly 2 columns"):
        delete_regions(data, BOXES, xy_slice=slice(0, 3))


@requires_shared
def test_delete_regions_antmaze_umaze_box():
    # maze-eval notes: the POR box x in [5, 10], y in [2, 7] (D4RL frame)
    # removes 300 of the 5383 antmaze-umaze-v0 10k transitions.
    data = load_dataset("antmaze-umaze-v0-10k")
    kept = delete_regions(data, [(5.0, 10.0, 2.0, 7.0)])
    assert len(data) - len(kept) == 300
