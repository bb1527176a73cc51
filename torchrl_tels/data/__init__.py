"""Offline data for TELS: datasets, replay buffers and subsets. It knows no algorithm and no environment."""

from torchrl_tels.data.datasets import (
    D4RL_REQUIRED_KEYS,
    EMBEDDED_DATASET,
    COLLECTED_DATASETS,
    EMBEDDED_DATASETS,
    DatasetError,
    embedded_dataset_path,
    load_dataset,
    minari_dataset_to_tensordict,
    shared_datasets_dir,
    user_datasets_dir,
)
from torchrl_tels.data.replay import make_offline_replay_buffer
from torchrl_tels.data.subsets import (
    PAPER_SUBSET_SIZES,
    SUBSET_MODES,
    delete_regions,
    points_in_boxes,
    subsample_transitions,
    subset_dataset,
    split_trajectories,
    subset_trajectories,
    trajectory_ids,
)

__all__ = [
    "D4RL_REQUIRED_KEYS",
    "EMBEDDED_DATASET",
    "COLLECTED_DATASETS",
    "EMBEDDED_DATASETS",
    "PAPER_SUBSET_SIZES",
    "SUBSET_MODES",
    "DatasetError",
    "delete_regions",
    "embedded_dataset_path",
    "load_dataset",
    "make_offline_replay_buffer",
    "minari_dataset_to_tensordict",
    "points_in_boxes",
    "shared_datasets_dir",
    "user_datasets_dir",
    "split_trajectories",
    "subsample_transitions",
    "subset_dataset",
    "subset_trajectories",
    "trajectory_ids",
]
