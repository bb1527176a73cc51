"""Offline data for TELS: datasets, replay buffers, subsets and tasks."""

from torchrl_tels.data.collect import collect_minari_dataset
from torchrl_tels.data.datasets import (
    D4RL_REQUIRED_KEYS,
    EMBEDDED_DATASET,
    DatasetError,
    embedded_dataset_path,
    load_dataset,
    minari_dataset_to_tensordict,
    shared_datasets_dir,
)
from torchrl_tels.data.replay import make_offline_replay_buffer
from torchrl_tels.data.subsets import (
    PAPER_SUBSET_SIZES,
    SUBSET_MODES,
    delete_regions,
    points_in_boxes,
    subsample_transitions,
    subset_dataset,
    subset_trajectories,
)
from torchrl_tels.data.tasks import (
    D4RL_REFERENCE_SCORES,
    Task,
    get_task,
    list_tasks,
    normalized_score,
    register_task,
)

__all__ = [
    "D4RL_REFERENCE_SCORES",
    "D4RL_REQUIRED_KEYS",
    "EMBEDDED_DATASET",
    "PAPER_SUBSET_SIZES",
    "SUBSET_MODES",
    "DatasetError",
    "Task",
    "collect_minari_dataset",
    "delete_regions",
    "embedded_dataset_path",
    "get_task",
    "list_tasks",
    "load_dataset",
    "make_offline_replay_buffer",
    "minari_dataset_to_tensordict",
    "normalized_score",
    "points_in_boxes",
    "register_task",
    "shared_datasets_dir",
    "subsample_transitions",
    "subset_dataset",
    "subset_trajectories",
]

from torchrl_tels.data import pointmaze  # noqa: E402,F401  (registers the PointMaze eval envs and tasks)
