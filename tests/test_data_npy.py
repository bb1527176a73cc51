"""Tests of load_dataset on pickled ``.npy`` files (TSRL's small-sample format).

TSRL writes each sample with ``np.save(path, np.array([dataset]))``: a one-element
object array holding a dict of D4RL arrays, i.e. a pickle. These tests build such
files from the shipped ``.npz`` sets and check that they load to the same values,
and that anything else a pickle could hold is refused before it runs.
"""

from __future__ import annotations

import importlib.resources
import os
import pickle

import numpy as np
import pytest
from numpy.lib import format as npy_format

from torchrl_tels.data import DatasetError, embedded_dataset_path, load_dataset

D4RL_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals")


def shipped_arrays(name: str) -> dict[str, np.ndarray]:
    with importlib.resources.as_file(embedded_dataset_path(name)) as path, np.load(path) as raw:
        return {key: raw[key] for key in D4RL_KEYS}


def save_like_tsrl(path, dataset: dict) -> None:
    """What TSRL's utils/generate_samples.py does: ``np.save(path, np.array([dataset]))``."""
    np.save(path, np.array([dataset]))


def write_npy_pickle(path, obj) -> None:
    """An object-array ``.npy`` header followed by a pickle of ``obj`` itself."""
    with open(path, "wb") as file:
        npy_format.write_array_header_1_0(
            file, {"descr": "|O", "fortran_order": False, "shape": (1,)}
        )
        pickle.dump(obj, file, protocol=4)


# --------------------------------------------------------------------------- #
# Files made the way TSRL makes them
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("name", ["hopper-medium-v2-10k", "antmaze-umaze-v0-10k"])
def test_tsrl_npy_loads_the_values_of_the_npz(name, tmp_path):
    arrays = shipped_arrays(name)
    path = tmp_path / f"{name}-ratio-100.npy"
    save_like_tsrl(path, arrays)
    # The file is what TSRL's loader reads (a pickle: allow_pickle=True).
    assert np.load(path, allow_pickle=True)[0].keys() == arrays.keys()

    data = load_dataset(path)
    np.testing.assert_array_equal(data["observation"].numpy(), arrays["observations"])
    np.testing.assert_array_equal(data["action"].numpy(), arrays["actions"])
    np.testing.assert_array_equal(data["next", "observation"].numpy(), arrays["next_observations"])
    np.testing.assert_array_equal(data["next", "reward"].numpy()[:, 0], arrays["rewards"])
    np.testing.assert_array_equal(data["next", "terminated"].numpy()[:, 0], arrays["terminals"])
    # Same episodes and flags as the shipped set read by name.
    assert (data == load_dataset(name)).all()
    # A string path resolves the same way.
    assert (load_dataset(str(path)) == data).all()


def test_npy_of_a_bare_dict_and_format_2_0_load(tmp_path):
    arrays = shipped_arrays("walker2d-medium-v2-10k")
    bare = tmp_path / "bare.npy"
    np.save(bare, arrays)  # a 0-d object array holding the dict
    assert np.load(bare, allow_pickle=True).shape == ()
    v2 = tmp_path / "v2.npy"
    with open(v2, "wb") as file:
        npy_format.write_array(file, np.array([arrays]), version=(2, 0))
    with open(v2, "rb") as file:
        assert npy_format.read_magic(file) == (2, 0)
    expected = load_dataset("walker2d-medium-v2-10k")
    assert (load_dataset(bare) == expected).all()
    assert (load_dataset(v2) == expected).all()


def test_npy_written_by_numpy_1_loads(tmp_path):
    # TSRL's files predate NumPy 2: NumPy 1.x's np.save pickles with protocol 3
    # (text GLOBAL opcodes) and names numpy.core where NumPy 2 names numpy._core.
    arrays = shipped_arrays("hopper-medium-replay-v2-10k")
    stream = pickle.dumps(np.array([arrays]), protocol=3)
    assert stream.count(b"cnumpy._core.multiarray\n_reconstruct\n") > 0
    stream = stream.replace(b"cnumpy._core.", b"cnumpy.core.")
    path = tmp_path / "numpy1.npy"
    with open(path, "wb") as file:
        npy_format.write_array_header_1_0(
            file, {"descr": "|O", "fortran_order": False, "shape": (1,)}
        )
        file.write(stream)
    assert (load_dataset(path) == load_dataset("hopper-medium-replay-v2-10k")).all()


def test_npy_timeouts_map_as_in_the_other_formats(tmp_path):
    # Two 3-step chains; the first ends in a timeout, the second in a terminal.
    observations = np.arange(6, dtype=np.float32)[:, None]
    arrays = {
        "observations": observations,
        "actions": np.zeros((6, 1), np.float32),
        "rewards": np.ones(6, np.float32),
        "next_observations": observations + 1,
        "terminals": np.array([0, 0, 0, 0, 0, 1], bool),
        "timeouts": np.array([0, 0, 1, 0, 0, 0], bool),
    }
    save_like_tsrl(tmp_path / "toy.npy", arrays)
    data = load_dataset(tmp_path / "toy.npy")
    assert data["episode"].tolist() == [0, 0, 0, 1, 1, 1]
    assert data["next", "truncated"][:, 0].tolist() == [False, False, True, False, False, False]
    assert data["next", "terminated"][:, 0].tolist() == [False] * 5 + [True]
    assert (data == load_dataset(arrays)).all()


# --------------------------------------------------------------------------- #
# What is refused
# --------------------------------------------------------------------------- #
class CallOnLoad:
    """A pickle payload: unpickling it calls ``func(*args)``."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


@pytest.mark.parametrize("payload", ["os.system", "open"])
def test_hostile_pickle_is_refused_before_it_runs(payload, tmp_path):
    def hostile_file(marker):
        if payload == "os.system":
            call, refused = CallOnLoad(os.system, f"touch {marker}"), "posix.system"
        else:
            call, refused = CallOnLoad(open, str(marker), "w"), "io.open"
        path = tmp_path / f"hostile-{marker.name}.npy"
        save_like_tsrl(path, {"observations": call, "actions": np.zeros(3)})
        return path, refused

    # The payload is live: NumPy's own unrestricted loader runs it.
    live_marker = tmp_path / "ran-under-np-load"
    live_path, _ = hostile_file(live_marker)
    np.load(live_path, allow_pickle=True)
    assert live_marker.exists()

    marker = tmp_path / "ran-under-load-dataset"
    path, refused = hostile_file(marker)
    with pytest.raises(DatasetError) as info:
        load_dataset(path)
    message = str(info.value)
    assert str(path) in message
    assert f"refused to unpickle the global '{refused}'" in message
    assert not marker.exists()


def test_numpy_global_outside_the_allowlist_is_refused(tmp_path):
    # Not every NumPy global is harmless (np.load would unpickle again).
    path = tmp_path / "nested.npy"
    save_like_tsrl(path, {"observations": CallOnLoad(np.load, "elsewhere.npy")})
    with pytest.raises(DatasetError, match=r"refused to unpickle the global 'numpy\.load'"):
        load_dataset(path)


def test_plain_numeric_npy_is_refused(tmp_path):
    path = tmp_path / "observations.npy"
    np.save(path, np.zeros((5, 3), np.float32))
    with pytest.raises(DatasetError, match=r"holds one float32 array of shape \(5, 3\); .*one dict of"):
        load_dataset(path)


@pytest.mark.parametrize(
    "content, message",
    [
        (np.array([None, None], dtype=object), r"an array of dtype object and shape \(2,\)"),
        ([np.zeros(3), np.zeros(3)], r"holds a list;"),
        ({"observations": [[0.0, 1.0]], "actions": np.zeros(1)}, r"'observations': list"),
        ({0: np.zeros(3)}, r"0: ndarray"),
    ],
    ids=["two-elements", "list", "dict-of-lists", "int-key"],
)
def test_unexpected_pickled_content_is_refused(content, message, tmp_path):
    path = tmp_path / "odd.npy"
    if isinstance(content, np.ndarray):
        np.save(path, content)
    else:
        holder = np.empty(1, dtype=object)
        holder[0] = content
        np.save(path, holder)
    with pytest.raises(DatasetError, match=message) as info:
        load_dataset(path)
    assert str(path) in str(info.value)
    assert "must hold one dict of D4RL arrays" in str(info.value)


def test_header_that_lies_about_its_pickle_is_refused(tmp_path):
    # Object-array header, but the pickle is a bare list, not an array.
    path = tmp_path / "list.npy"
    write_npy_pickle(path, [np.zeros(3)])
    with pytest.raises(DatasetError, match="holds a pickled list, not an array"):
        load_dataset(path)


def test_dict_with_non_d4rl_keys_is_reported_as_missing_keys(tmp_path):
    path = tmp_path / "other.npy"
    save_like_tsrl(path, {"obs": np.zeros((3, 2)), "act": np.zeros((3, 1))})
    with pytest.raises(DatasetError, match=r"missing key\(s\) \['observations'"):
        load_dataset(path)


@pytest.mark.parametrize(
    "raw",
    [b"not an npy file at all", b"\x93NUMPY\x03\x00" + b"\x00" * 16],
    ids=["no-magic", "version-3"],
)
def test_malformed_npy_is_one_dataset_error(raw, tmp_path):
    path = tmp_path / "bad.npy"
    path.write_bytes(raw)
    with pytest.raises(DatasetError, match=r"bad\.npy: (could not be read|\.npy format version 3\.0)"):
        load_dataset(path)


def test_truncated_pickle_is_one_dataset_error(tmp_path):
    path = tmp_path / "cut.npy"
    save_like_tsrl(path, {"observations": np.zeros((100, 3))})
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(DatasetError, match="cut.npy: could not be read"):
        load_dataset(path)


def test_missing_npy_path_is_reported(tmp_path):
    with pytest.raises(DatasetError, match="Dataset file not found: .*absent.npy"):
        load_dataset(str(tmp_path / "absent.npy"))
