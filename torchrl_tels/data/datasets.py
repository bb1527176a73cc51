"""Loading offline RL datasets into TorchRL's transition layout.

Every loader in this module returns one flat :class:`~tensordict.TensorDict`
with one row per transition, laid out the way TorchRL collectors and losses
expect it::

    observation              float32 (N, *obs_shape)
    action                   float32 (N, *act_shape)
    episode                  int64   (N,)
    ("next", "observation")  float32 (N, *obs_shape)
    ("next", "reward")       float32 (N, 1)
    ("next", "terminated")   bool    (N, 1)
    ("next", "truncated")    bool    (N, 1)
    ("next", "done")         bool    (N, 1)

``episode`` numbers the trajectories 0, 1, 2, ... in dataset order, and the
last transition of every trajectory has ``("next", "done")`` set.

Sources understood by :func:`load_dataset`:

* a D4RL-style ``.npz`` or ``.hdf5`` file (``observations``, ``actions``,
  ``rewards``, ``next_observations``, ``terminals``, optional ``timeouts``), or
  a ``.npy`` holding a pickled dict of those arrays (how TSRL ships its small
  samples), unpickled without calling anything but NumPy's array rebuilders;
* an in-memory mapping with the same keys;
* a dataset shipped inside the package: the eleven 10k sets of the paper's
  Table 1 (:data:`EMBEDDED_DATASETS`; ``"embedded"``/``"default"`` name
  ``"hopper-medium-v2-10k"``);
* a set too large to ship (:data:`COLLECTED_DATASETS`: AntMaze medium and
  large at 100k), from the shared folder or the user's
  (:func:`user_datasets_dir`), or else an error naming the command that
  makes it;
* a name of a file in the workplace's shared dataset folder (see
  :func:`shared_datasets_dir`);
* a Minari dataset id (``"mujoco/hopper/medium-v0"``), read with Minari's own
  episode API from ``MINARI_DATASETS_PATH`` and downloaded when Minari's remote
  support is installed.

Anything malformed raises :class:`DatasetError` (a :class:`ValueError`) naming
the problem.
"""

from __future__ import annotations

import importlib.resources
import importlib.util
import os
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from numpy.lib import format as npy_format
from tensordict import TensorDict

from torchrl_tels.errors import DatasetError

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

__all__ = [
    "DatasetError",
    "D4RL_REQUIRED_KEYS",
    "EMBEDDED_DATASET",
    "EMBEDDED_DATASETS",
    "COLLECTED_DATASETS",
    "user_datasets_dir",
    "load_dataset",
    "minari_dataset_to_tensordict",
    "embedded_dataset_path",
    "shared_datasets_dir",
]

DatasetSource = str | os.PathLike | Mapping[str, Any]

#: Keys a D4RL ``qlearning_dataset``-style source must provide.
D4RL_REQUIRED_KEYS: tuple[str, ...] = (
    "observations",
    "actions",
    "rewards",
    "next_observations",
    "terminals",
)
#: Optional D4RL key marking time-limit truncations.
D4RL_OPTIONAL_KEYS: tuple[str, ...] = ("timeouts",)

#: The default dataset, reached by the aliases ``"embedded"``/``"default"``.
EMBEDDED_DATASET = "hopper-medium-v2-10k"
#: Datasets shipped in ``torchrl_tels/data/assets`` (``<name>.npz``): the
#: reduced-size D4RL samples of the paper's Table 1 and the Adroit sets of its
#: Tables 1 and 6 rebuilt from DAPG, so that each runs from an installed package
#: alone (attribution in ``ATTRIBUTION.md``).
EMBEDDED_DATASETS: tuple[str, ...] = (
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
    "door-human-v1",
    "pen-expert-v1-10k",
    "door-expert-v1-10k",
    "hammer-expert-v1-10k",
    "relocate-expert-v1-10k",
)
_EMBEDDED_ALIASES = ("embedded", "default")

#: Sets too large to ship, made on the user's machine: name -> the command that makes it (run from the
#: repository root; it writes ``<user_datasets_dir()>/<name>.npz``).
COLLECTED_DATASETS: dict[str, str] = {
    f"antmaze-{name}-v2-100k": f"python recipes/collect_antmaze.py {name}"
    for name in ("medium-play", "medium-diverse", "large-play", "large-diverse")
}
#: Environment variable naming the user's dataset folder (default ``~/.cache/torchrl_tels/datasets``).
USER_DATASETS_ENV = "TORCHRL_TELS_DATA"

#: Environment variable overriding the location of the shared dataset folder.
SHARED_DATASETS_ENV = "TORCHRL_TELS_SHARED_DATASETS"
#: Sub-folders of the shared dataset folder searched for ``<name>.npz``.
_SHARED_SUBDIRS = ("d4rl-10k", "antmaze")

_FILE_SUFFIXES = (".npz", ".npy", ".hdf5", ".h5")


# --------------------------------------------------------------------------- #
# Locating sources
# --------------------------------------------------------------------------- #
def shared_datasets_dir() -> Path | None:
    """Return the workplace's shared dataset folder, or ``None`` if absent.

    This is ``../shared/datasets`` relative to the repository root (the
    folder holding ``d4rl-10k/``). The environment variable
    ``TORCHRL_TELS_SHARED_DATASETS`` overrides the location, which is useful
    when the package is installed outside the repository.
    """
    override = os.environ.get(SHARED_DATASETS_ENV)
    if override:
        candidate = Path(override).expanduser()
    else:
        repo_root = Path(__file__).resolve().parents[2]
        candidate = repo_root.parent / "shared" / "datasets"
    return candidate if candidate.is_dir() else None


def embedded_dataset_path(name: str = EMBEDDED_DATASET) -> Traversable:
    """Return the packaged asset for ``name`` as an importlib resource.

    Args:
        name: one of :data:`EMBEDDED_DATASETS`, or one of the aliases
            ``"embedded"`` / ``"default"``.

    Returns:
        The resource; use :func:`importlib.resources.as_file` to get a
        filesystem path.

    Raises:
        DatasetError: if no such asset is shipped.
    """
    if name in _EMBEDDED_ALIASES:
        name = EMBEDDED_DATASET
    # Only known names: an arbitrary string must not become a path inside the
    # installed package.
    if name not in EMBEDDED_DATASETS:
        raise DatasetError(
            f"No embedded dataset named {name!r}; shipped: {list(EMBEDDED_DATASETS)}."
        )
    resource = importlib.resources.files("torchrl_tels.data").joinpath(
        "assets", f"{name}.npz"
    )
    if not resource.is_file():  # an install that lost its package data
        raise DatasetError(
            f"The embedded dataset {name!r} is missing from this installation "
            f"({resource}); reinstall torchrl-tels."
        )
    return resource


def _looks_like_file_path(source: str) -> bool:
    return source.endswith(_FILE_SUFFIXES) or source.startswith((".", "~", os.sep))


def _minari_remote_support() -> str | None:
    """Return why Minari cannot download, or ``None`` if it has what it needs."""
    remote = os.environ.get("MINARI_REMOTE", "hf://farama-minari")
    scheme = remote.split("://", maxsplit=1)[0]
    module = {"hf": "huggingface_hub", "gcp": "google.cloud.storage"}.get(scheme)
    if module is None:
        return f"unknown MINARI_REMOTE scheme {scheme!r}"
    try:
        found = importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        found = False
    if not found:
        extra = "hf" if scheme == "hf" else "gcs"
        return (
            f"Minari's {scheme!r} remote needs the {module!r} package "
            f'(pip install "minari[{extra}]")'
        )
    return None


def _minari_local_path(dataset_id: str) -> Path:
    from minari.storage.datasets_root_dir import get_dataset_path

    return Path(get_dataset_path(dataset_id))


def recorded_env_id(source: DatasetSource) -> str | None:
    """The Gymnasium id of the environment a local Minari dataset recorded, else ``None``.

    Lets a user's own dataset be evaluated where it was collected. Prefers the
    dataset's evaluation env over its collection env, as Minari does.
    """
    if not isinstance(source, str) or Path(source).suffix in _FILE_SUFFIXES:
        return None
    try:
        local_path = _minari_local_path(source)
    except Exception:  # minari missing, or not an id Minari can parse
        return None
    if not (local_path / "data").is_dir():
        return None
    import minari

    try:
        dataset = minari.load_dataset(source)
    except Exception:
        return None
    for spec in (getattr(dataset.spec, "eval_env_spec", None), getattr(dataset.spec, "env_spec", None)):
        if spec is not None and getattr(spec, "id", None):
            return spec.id
    return None


def user_datasets_dir() -> Path:
    """The folder where collectors write, and :func:`load_dataset` finds, the sets of
    :data:`COLLECTED_DATASETS`: ``$TORCHRL_TELS_DATA``, or ``~/.cache/torchrl_tels/datasets``."""
    override = os.environ.get(USER_DATASETS_ENV)
    return Path(override).expanduser() if override else Path.home() / ".cache" / "torchrl_tels" / "datasets"


def _collected_dataset(source: str) -> Path:
    """The file of a :data:`COLLECTED_DATASETS` name: the shared folder's copy, else the user's."""
    shared = shared_datasets_dir()
    candidates = [*(shared / subdir / f"{source}.npz" for subdir in _SHARED_SUBDIRS if shared is not None),
                  user_datasets_dir() / f"{source}.npz"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise DatasetError(
        f"{source} is not in {user_datasets_dir()}; make it with: {COLLECTED_DATASETS[source]}"
    )


# --------------------------------------------------------------------------- #
# Public entry point
# --------------------------------------------------------------------------- #
def load_dataset(
    source: DatasetSource,
    *,
    observation_keys: Sequence[str] | None = None,
    goal_key: str | None = "desired_goal",
    download: bool = True,
) -> TensorDict:
    """Load an offline dataset as a flat TensorDict of transitions.

    Resolution order for a string ``source``:

    1. an existing file (``.npz``, ``.npy``, ``.hdf5``/``.h5``), or a string
       that looks like a path (has one of these suffixes or starts with ``.``,
       ``~``, ``/``), which must then exist;
    2. a dataset shipped with the package (:data:`EMBEDDED_DATASETS`, e.g.
       ``"walker2d-medium-v2-10k"``; ``"embedded"``/``"default"`` for
       ``"hopper-medium-v2-10k"``);
    3. ``<shared_datasets_dir()>/d4rl-10k/<source>.npz``;
    4. a Minari dataset id, local under ``MINARI_DATASETS_PATH`` (default
       ``~/.minari/datasets``), downloaded if ``download`` and Minari's remote
       support is installed.

    A ``.npy`` file must hold one dict of D4RL arrays, pickled by ``np.save``
    (a bare dict, or TSRL's one-element array of it). Only the globals NumPy
    needs to rebuild arrays are unpickled; any other refuses the file before
    anything in it runs.

    For D4RL-style data, trajectories end where ``terminals`` or ``timeouts``
    is set, where ``next_observations[i] != observations[i + 1]``, and at the
    last row. An end that is not a terminal is a truncation
    (``("next", "truncated")``); ``done = terminated | truncated``.

    For Minari data, transitions are ``obs[t] -> obs[t + 1]`` within each
    episode, with Minari's termination/truncation flags. The last transition
    of an episode that carries neither flag (a recording cut short) is marked
    truncated so that every episode ends with ``done``. Dict observations are
    flattened into one vector, concatenating the entries in ``observation_keys``
    order (default: all entries, in the observation space's order, which for
    Gymnasium's ``Dict`` is sorted by key); when the dict has a ``goal_key``
    entry it is also stored on its own under ``goal_key`` (and
    ``("next", goal_key)``).

    Args:
        source: file path, in-memory mapping of D4RL arrays, dataset name or
            Minari dataset id.

    Keyword Args:
        observation_keys: for dict observations (Minari), the entries to
            concatenate, in order.
        goal_key: for dict observations (Minari), entry also kept as a separate
            key; ``None`` to keep none.
        download: let Minari download a dataset missing locally.

    Returns:
        A :class:`~tensordict.TensorDict` with ``batch_size=[N]`` (see module
        docstring for the layout).

    Raises:
        DatasetError: unknown source (the message lists every place looked
            at), missing keys, mismatched lengths, empty data, non-finite
            values or dtypes that cannot be cast.

    Examples:
        >>> data = load_dataset("hopper-medium-v2-10k")
        >>> data["observation"].shape
        torch.Size([9013, 11])
        >>> int(data["episode"].max()) + 1
        21
    """
    if isinstance(source, Mapping):
        return _d4rl_arrays_to_tensordict(dict(source), source_name="<mapping>")
    if isinstance(source, os.PathLike):
        return _load_d4rl_file(Path(source))
    if not isinstance(source, str):
        raise DatasetError(
            f"Unsupported dataset source of type {type(source).__name__}: expected "
            "a path, a dataset name, a Minari id or a mapping of D4RL arrays."
        )

    looked_at: list[str] = []
    path = Path(source).expanduser()
    if path.is_file():
        return _load_d4rl_file(path)
    if _looks_like_file_path(source):
        raise DatasetError(f"Dataset file not found: {str(path)!r}.")
    looked_at.append(f"file {str(path)!r}")

    # A shipped name never falls through to the shared folder: an install that
    # lost its package data should say so, not load whatever else is around.
    if source in EMBEDDED_DATASETS or source in _EMBEDDED_ALIASES:
        resource = embedded_dataset_path(source)
        with importlib.resources.as_file(resource) as resource_path:
            return _load_d4rl_file(resource_path, source_name=source)
    looked_at.append(f"embedded datasets {[*EMBEDDED_DATASETS, *_EMBEDDED_ALIASES]}")
    if source in COLLECTED_DATASETS:
        return _load_d4rl_file(_collected_dataset(source), source_name=source)

    shared = shared_datasets_dir()
    if shared is None:
        looked_at.append(
            f"shared dataset folder (absent; set {SHARED_DATASETS_ENV} to point to it)"
        )
    else:
        for subdir in _SHARED_SUBDIRS:
            candidate = shared / subdir / f"{source}.npz"
            if candidate.is_file():
                return _load_d4rl_file(candidate)
            looked_at.append(f"shared file {str(candidate)!r}")

    return _load_minari(
        source,
        observation_keys=observation_keys,
        goal_key=goal_key,
        download=download,
        looked_at=looked_at,
    )


# --------------------------------------------------------------------------- #
# D4RL-style files and arrays
# --------------------------------------------------------------------------- #
def _load_d4rl_file(path: Path, source_name: str | None = None) -> TensorDict:
    source_name = source_name or str(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            # allow_pickle=False: these files must hold plain arrays only.
            with np.load(path, allow_pickle=False) as archive:
                arrays = {key: archive[key] for key in archive.files}
        elif suffix == ".npy":
            arrays = _read_pickled_npy(path, source_name)
        elif suffix in (".hdf5", ".h5"):
            import h5py

            with h5py.File(path, "r") as file:
                # D4RL files also hold groups (``infos/``, ``metadata/``):
                # only top-level datasets are transition arrays.
                arrays = {
                    key: item[()]
                    for key, item in file.items()
                    if isinstance(item, h5py.Dataset)
                }
        else:
            raise DatasetError(
                f"{source_name}: unsupported file type {suffix!r}; expected one of "
                f"{list(_FILE_SUFFIXES)}."
            )
    except DatasetError:
        raise
    except Exception as err:  # corrupt archive, pickled objects, bad HDF5...
        raise DatasetError(f"{source_name}: could not be read ({err}).") from err
    return _d4rl_arrays_to_tensordict(arrays, source_name=source_name)


# What ``np.save`` writes for an object array of a dict of numeric arrays needs
# exactly these globals; each only builds an array or a dtype from the data it
# is given. ``_reconstruct`` is taken from a live array so that it is this
# NumPy's own, under either module name a file may carry (``numpy.core``
# before NumPy 2, ``numpy._core`` since). A dict needs no global: pickle
# protocols >= 1 have an opcode for it.
_NPY_RECONSTRUCT = np.empty(0).__reduce__()[0]
_NPY_ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy.core.multiarray", "_reconstruct"): _NPY_RECONSTRUCT,
    ("numpy._core.multiarray", "_reconstruct"): _NPY_RECONSTRUCT,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class _ArraysOnlyUnpickler(pickle.Unpickler):
    """An unpickler that resolves no global but :data:`_NPY_ALLOWED_GLOBALS`.

    Every callable a pickle can call reaches it through :meth:`find_class`
    (the GLOBAL, STACK_GLOBAL, INST and OBJ opcodes and copyreg's extension
    codes), so refusing here refuses before anything named in the file runs.
    """

    def __init__(self, file: Any, source_name: str) -> None:
        super().__init__(file)
        self._source_name = source_name

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _NPY_ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise DatasetError(
                f"{self._source_name}: refused to unpickle the global "
                f"'{module}.{name}'; a .npy dataset may only hold NumPy arrays in "
                "a dict, so the file was not loaded and nothing it names was called."
            ) from None


def _read_pickled_npy(path: Path, source_name: str) -> dict[str, np.ndarray]:
    """The dict of arrays in a ``.npy`` that ``np.save`` wrote from a dict.

    Reads what ``np.load(path, allow_pickle=True)`` would, but unpickles with
    :class:`_ArraysOnlyUnpickler` instead of :mod:`pickle`'s trust-everything
    default.
    """

    def refuse(what: str) -> DatasetError:
        return DatasetError(
            f"{source_name}: holds {what}; a .npy dataset must hold one dict of "
            "D4RL arrays, as written by np.save(path, {'observations': ..., ...}). "
            "Save plain arrays with np.savez instead."
        )

    with open(path, "rb") as file:
        version = npy_format.read_magic(file)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(file)
        elif version == (2, 0):
            shape, _, dtype = npy_format.read_array_header_2_0(file)
        else:  # 3.0 only adds UTF-8 field names, which no object array has
            raise DatasetError(
                f"{source_name}: .npy format version {version[0]}.{version[1]} is "
                "not supported here; expected 1.0 or 2.0."
            )
        # Only an object array is stored as a pickle; anything else is one
        # plain array, which cannot be a whole dataset.
        if dtype != np.dtype(object):
            raise refuse(f"one {dtype} array of shape {shape}")
        content = _ArraysOnlyUnpickler(file, source_name).load()

    # The header's promise is checked on what was actually unpickled.
    if not isinstance(content, np.ndarray):
        raise refuse(f"a pickled {type(content).__name__}, not an array")
    if content.dtype != np.dtype(object) or content.size != 1:
        raise refuse(f"an array of dtype {content.dtype} and shape {content.shape}")
    content = content.item()
    if not isinstance(content, dict):
        raise refuse(f"a {type(content).__name__}")
    not_arrays = [
        f"{key!r}: {type(value).__name__}"
        for key, value in content.items()
        if not (isinstance(key, str) and isinstance(value, np.ndarray))
    ]
    if not_arrays:
        entries = ", ".join(not_arrays)
        raise refuse(f"a dict with entries that are not name: array ({entries})")
    return content


def _as_numeric(array: Any, key: str, source_name: str) -> np.ndarray:
    array = np.asarray(array)
    # bool, signed/unsigned int and float can be cast to float32; complex,
    # strings and objects cannot be, meaningfully.
    if array.dtype.kind not in "biuf":
        raise DatasetError(
            f"{source_name}: {key!r} has dtype {array.dtype}, which cannot be cast "
            "to a numeric tensor."
        )
    return array


def _as_float32(array: np.ndarray, key: str, source_name: str) -> np.ndarray:
    with np.errstate(over="ignore"):  # reported below as non-finite values
        out = array.astype(np.float32, copy=False)
    # Checked after the cast: float64 values beyond float32's range become inf.
    finite = np.isfinite(out)
    if not finite.all():
        bad_rows = np.flatnonzero(~finite.reshape(len(out), -1).all(axis=1))
        raise DatasetError(
            f"{source_name}: {key!r} has {int((~finite).sum())} NaN/inf value(s) "
            f"(first at row {int(bad_rows[0])}) after casting to float32."
        )
    return np.ascontiguousarray(out)


def _as_flags(array: np.ndarray, key: str, source_name: str) -> np.ndarray:
    if array.dtype != np.bool_:
        valid = np.isin(array, (0, 1))
        if not valid.all():
            first = int(np.flatnonzero(~valid.reshape(len(array), -1).all(axis=1))[0])
            raise DatasetError(
                f"{source_name}: {key!r} must hold booleans or 0/1 values; found "
                f"{array.reshape(len(array), -1)[first].tolist()} at row {first}."
            )
    return array.astype(bool)


def _per_step(array: np.ndarray, key: str, source_name: str) -> np.ndarray:
    """Check a per-transition scalar array is (N,) or (N, 1), return (N,)."""
    if array.ndim == 2 and array.shape[1] == 1:
        array = array[:, 0]
    if array.ndim != 1:
        raise DatasetError(
            f"{source_name}: {key!r} must have shape (N,) or (N, 1), got "
            f"{tuple(array.shape)}."
        )
    return array


def _with_feature_dim(array: np.ndarray) -> np.ndarray:
    # A scalar observation/action per step becomes a one-feature vector.
    return array[:, None] if array.ndim == 1 else array


def _d4rl_arrays_to_tensordict(
    arrays: dict[str, Any],
    *,
    source_name: str,
    extra: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> TensorDict:
    """Validate D4RL-style arrays and convert them to the transition layout.

    ``extra`` maps a key to ``(value, next_value)`` arrays stored as ``key``
    and ``("next", key)`` (used for goals of dict observations).
    """
    missing = [key for key in D4RL_REQUIRED_KEYS if key not in arrays]
    if missing:
        raise DatasetError(
            f"{source_name}: missing key(s) {missing}; found {sorted(arrays)}. "
            f"A D4RL-style dataset needs {list(D4RL_REQUIRED_KEYS)} and optionally "
            f"{list(D4RL_OPTIONAL_KEYS)}."
        )
    present = [k for k in (*D4RL_REQUIRED_KEYS, *D4RL_OPTIONAL_KEYS) if k in arrays]
    raw = {key: _as_numeric(arrays[key], key, source_name) for key in present}

    for key, array in raw.items():
        if array.ndim == 0:
            raise DatasetError(
                f"{source_name}: {key!r} is a scalar, not per-step data."
            )
    lengths = {key: int(array.shape[0]) for key, array in raw.items()}
    if len(set(lengths.values())) != 1:
        raise DatasetError(
            f"{source_name}: arrays have mismatched lengths {lengths}; every key "
            "needs one row per transition."
        )
    num_transitions = lengths["observations"]
    if num_transitions == 0:
        raise DatasetError(f"{source_name}: the dataset is empty (0 transitions).")

    observation = _with_feature_dim(raw["observations"])
    next_observation = _with_feature_dim(raw["next_observations"])
    if observation.shape != next_observation.shape:
        raise DatasetError(
            f"{source_name}: 'observations' {tuple(observation.shape)} and "
            f"'next_observations' {tuple(next_observation.shape)} differ in shape."
        )
    observation = _as_float32(observation, "observations", source_name)
    next_observation = _as_float32(next_observation, "next_observations", source_name)
    action = _as_float32(_with_feature_dim(raw["actions"]), "actions", source_name)
    reward = _as_float32(
        _per_step(raw["rewards"], "rewards", source_name), "rewards", source_name
    )
    terminated = _as_flags(
        _per_step(raw["terminals"], "terminals", source_name), "terminals", source_name
    )
    if "timeouts" in raw:
        timeouts = _as_flags(
            _per_step(raw["timeouts"], "timeouts", source_name), "timeouts", source_name
        )
    else:
        timeouts = np.zeros(num_transitions, dtype=bool)

    # Episode ends: flagged ends, breaks in the observation chain, the last row.
    chain_break = np.zeros(num_transitions, dtype=bool)
    chain_break[:-1] = (
        (next_observation[:-1] != observation[1:])
        .reshape(num_transitions - 1, -1)
        .any(axis=1)
    )
    episode_end = terminated | timeouts | chain_break
    episode_end[-1] = True
    truncated = episode_end & ~terminated
    done = terminated | truncated
    # Row i belongs to the episode counting the ends strictly before it.
    episode = np.concatenate(([0], np.cumsum(episode_end[:-1]))).astype(np.int64)

    data = TensorDict(
        {
            "observation": torch.from_numpy(observation),
            "action": torch.from_numpy(action),
            "episode": torch.from_numpy(episode),
            "next": {
                "observation": torch.from_numpy(next_observation),
                "reward": torch.from_numpy(reward).unsqueeze(-1),
                "terminated": torch.from_numpy(terminated).unsqueeze(-1),
                "truncated": torch.from_numpy(truncated).unsqueeze(-1),
                "done": torch.from_numpy(done).unsqueeze(-1),
            },
        },
        batch_size=[num_transitions],
    )
    for key, (value, next_value) in (extra or {}).items():
        value = _as_float32(_with_feature_dim(np.asarray(value)), key, source_name)
        next_value = _as_float32(
            _with_feature_dim(np.asarray(next_value)), key, source_name
        )
        data.set(key, torch.from_numpy(value))
        data.set(("next", key), torch.from_numpy(next_value))
    return data


# --------------------------------------------------------------------------- #
# Minari datasets
# --------------------------------------------------------------------------- #
def _load_minari(
    dataset_id: str,
    *,
    observation_keys: Sequence[str] | None,
    goal_key: str | None,
    download: bool,
    looked_at: list[str],
) -> TensorDict:
    import minari

    local_path = _minari_local_path(dataset_id)
    if not (local_path / "data").is_dir():
        looked_at.append(f"Minari dataset {str(local_path)!r} (MINARI_DATASETS_PATH)")
        why_not = (
            "download disabled (download=False)"
            if not download
            else _minari_remote_support()
        )
        if why_not is not None:
            raise DatasetError(
                f"Unknown dataset {dataset_id!r}. Looked for: "
                + "; ".join(looked_at)
                + f". No download attempted: {why_not}. To use a Minari dataset "
                "offline, run `minari download <id>` where a network is available "
                "and copy the folder under MINARI_DATASETS_PATH; or pass a path to "
                "a D4RL-style .npz/.hdf5 file."
            )
        try:
            minari.download_dataset(dataset_id)
        except Exception as err:  # no network, unknown remote id, ...
            raise DatasetError(
                f"Unknown dataset {dataset_id!r}. Looked for: "
                + "; ".join(looked_at)
                + f". Downloading it with Minari failed: {err}"
            ) from err

    try:
        dataset = minari.load_dataset(dataset_id)
    except Exception as err:
        raise DatasetError(f"{dataset_id}: Minari could not open it ({err}).") from err
    return minari_dataset_to_tensordict(
        dataset, observation_keys=observation_keys, goal_key=goal_key
    )


def _flatten_space_values(
    value: Any, keys: Sequence[str] | None, source_name: str
) -> np.ndarray:
    """Concatenate (possibly dict/tuple) per-step values into (T, D) arrays."""
    if isinstance(value, Mapping):
        if keys is None:
            keys = list(value)
        unknown = [key for key in keys if key not in value]
        if unknown:
            raise DatasetError(
                f"{source_name}: observation key(s) {unknown} not in the dict "
                f"observation; available: {list(value)}."
            )
        parts = [_flatten_space_values(value[key], None, source_name) for key in keys]
        return np.concatenate(parts, axis=1)
    if isinstance(value, tuple):
        parts = [_flatten_space_values(item, None, source_name) for item in value]
        return np.concatenate(parts, axis=1)
    value = _as_numeric(value, "observations/actions", source_name)
    return value.reshape(len(value), -1)


def minari_dataset_to_tensordict(
    dataset: Any,
    *,
    observation_keys: Sequence[str] | None = None,
    goal_key: str | None = "desired_goal",
) -> TensorDict:
    """Convert an open :class:`minari.MinariDataset` to the transition layout.

    Episodes are read with :meth:`~minari.MinariDataset.iterate_episodes`;
    see :func:`load_dataset` for the conversion rules.
    """
    source_name = str(dataset.spec.dataset_id)
    columns: dict[str, list[np.ndarray]] = {
        key: [] for key in (*D4RL_REQUIRED_KEYS, "timeouts")
    }
    goals: list[np.ndarray] = []
    next_goals: list[np.ndarray] = []
    has_goal = True
    for episode in dataset.iterate_episodes():
        num_steps = len(episode)
        if num_steps == 0:
            continue
        observations = episode.observations
        is_dict = isinstance(observations, Mapping)
        if observation_keys is not None and not is_dict:
            raise DatasetError(
                f"{source_name}: observation_keys={list(observation_keys)} given "
                "but the observations are not a dict."
            )
        if is_dict or isinstance(observations, tuple):
            flat = _flatten_space_values(observations, observation_keys, source_name)
        else:
            flat = _with_feature_dim(
                _as_numeric(observations, "observations", source_name)
            )
        if len(flat) != num_steps + 1:
            raise DatasetError(
                f"{source_name}: episode {episode.id} has {len(flat)} observations "
                f"for {num_steps} steps; Minari episodes store steps + 1."
            )
        actions = episode.actions
        if isinstance(actions, (Mapping, tuple)):
            actions = _flatten_space_values(actions, None, source_name)
        terminations = np.asarray(episode.terminations, dtype=bool).reshape(-1)
        truncations = np.asarray(episode.truncations, dtype=bool).reshape(-1)
        # A recording cut short has neither flag on its last step: it is still
        # the end of this trajectory, i.e. a truncation.
        truncations = truncations.copy()
        truncations[-1] |= not terminations[-1]

        columns["observations"].append(flat[:-1])
        columns["next_observations"].append(flat[1:])
        columns["actions"].append(np.asarray(actions))
        columns["rewards"].append(np.asarray(episode.rewards))
        columns["terminals"].append(terminations)
        columns["timeouts"].append(truncations)
        if is_dict and goal_key is not None and goal_key in observations:
            goal = np.asarray(observations[goal_key]).reshape(num_steps + 1, -1)
            goals.append(goal[:-1])
            next_goals.append(goal[1:])
        else:
            has_goal = False

    if not columns["observations"]:
        raise DatasetError(f"{source_name}: the dataset is empty (0 transitions).")
    arrays = {key: np.concatenate(parts) for key, parts in columns.items()}
    extra = None
    if has_goal and goals:
        extra = {goal_key: (np.concatenate(goals), np.concatenate(next_goals))}
    return _d4rl_arrays_to_tensordict(arrays, source_name=source_name, extra=extra)
