"""Where a run is in Algorithm 1, saved so that a killed run continues bitwise where it stopped."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchrl_tels import training
import torch

from torchrl_tels.config import check_folder_creatable, check_same_run, RunSpec, training_config
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.training import get_rng_state, set_rng_state

__all__ = ["RunState", "start_run"]


@dataclass
class RunState:
    """Where a run is in Algorithm 1, and what it has produced so far.

    ``stage`` moves ``"tsidm"`` → ``"policy"`` → ``"done"``; ``candidate`` and
    ``step`` say where in that stage. Module and optimizer states travel beside
    it in ``state.pt`` (see :meth:`save`), so a killed run continues where its
    last checkpoint left it.
    """

    config: dict
    stage: str = "tsidm"
    candidate: int = 0
    step: int = 0
    wandb_id: str | None = None
    wall: dict = field(default_factory=dict)
    beta_results: list = field(default_factory=list)
    tsidm_history: dict = field(default_factory=dict)
    policy_history: dict = field(default_factory=dict)
    evaluations: list = field(default_factory=list)
    modules: dict = field(default_factory=dict)
    rng: dict | None = None
    per_seed: list = field(default_factory=list)  # with ``seeds``: each seed's record (:meth:`seed_record`)

    def __post_init__(self):
        self._clocks: list[_Stopwatch] = []  # the running :meth:`time` spans, brought up to date by :meth:`save`
        self._seed_states: list[RunState] = []  # a stacked run's :meth:`seed_states`, recorded by :meth:`save`

    @classmethod
    def start(cls, spec: RunSpec, path: Path) -> "RunState":
        """A fresh state, or with ``resume=true`` the one in ``path`` (checked to be the same run)."""
        config = training_config(spec.config)
        if not (spec.resume and path.exists()):
            return cls(config=config)
        saved = training.load_training_state(path)
        check_same_run(saved.get("config"), config, f"checkpoint {path}")
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in saved.items() if k in fields and k != "config"}, config=config)

    def save(self, path: Path, **modules: Any) -> None:
        """Writes this state, ``modules`` (state dicts) and, with them, the RNG streams atomically.

        The wall-clock spans still running (:meth:`time`) are counted up to now first, so a
        resumed run's times include the work before the interruption."""
        for clock in self._clocks:
            clock.update()
        if self._seed_states:
            self.per_seed = [state.seed_record() for state in self._seed_states]
        self.modules = modules
        self.rng = get_rng_state() if modules else None
        # A shallow record: torch.save writes the tensors as they are, no copy needed.
        training.save_training_state(path, {f.name: getattr(self, f.name) for f in dataclasses.fields(self)})

    def resumes(self, stage: str, candidate: int = 0) -> bool:
        """Whether this state holds a checkpoint inside ``stage`` (and β candidate) to continue."""
        return self.stage == stage and self.candidate == candidate and self.step > 0 and bool(self.modules)

    def restore(self, **modules: Any) -> None:
        """Loads the saved module states into ``modules`` and the RNG streams (after :meth:`resumes`)."""
        for name, module in modules.items():
            module.load_state_dict(self.modules[name])
        set_rng_state(self.rng)

    #: what a seed of a ``seeds`` run keeps of its own; the rest (stage, step, modules) is the run's
    SEED_FIELDS = ("beta_results", "tsidm_history", "policy_history", "evaluations", "wall")

    def seed_record(self) -> dict:
        return {name: getattr(self, name) for name in self.SEED_FIELDS}

    @classmethod
    def from_seed_record(cls, record: dict) -> "RunState":
        return cls(config={}, **{name: record[name] for name in cls.SEED_FIELDS})

    def seed_states(self, n_seeds: int, stacked: bool) -> list["RunState"]:
        """Where each seed records its own results: this state itself for a plain run; for a stacked run one state
        per seed, read from ``per_seed`` and written back into it by every :meth:`save`."""
        if not stacked:
            return [self]
        self._seed_states = ([RunState.from_seed_record(r) for r in self.per_seed] if self.per_seed
                             else [RunState(config={}) for _ in range(n_seeds)])
        return self._seed_states

    def time(self, key: str):
        """A context that adds the wall-clock time it spans to ``wall[key]``."""
        return _Stopwatch(self.wall, key, self._clocks)


class _Stopwatch:
    def __init__(self, wall: dict, key: str, running: list):
        self.wall, self.key, self.running = wall, key, running

    def __enter__(self):
        self.start = time.perf_counter() - self.wall.get(self.key, 0.0)
        self.running.append(self)
        return self

    def update(self):
        self.wall[self.key] = time.perf_counter() - self.start

    def __exit__(self, *exc):
        self.update()
        self.running.remove(self)


def start_run(spec: RunSpec) -> tuple[RunFolder, RunState]:
    """Sets torch's threads and global seed, checks ``run_dir`` may take this run (nothing is created yet) and
    loads the run's state: fresh, or with ``resume=true`` the one saved there."""
    torch.set_num_threads(spec.threads)
    torch.manual_seed(spec.seed)
    folder = RunFolder(check_folder_creatable(spec.run_dir))
    folder.check_free(resume=spec.resume, overwrite=spec.overwrite)
    run = RunState.start(spec, folder.state_path)
    if spec.resume and folder.state_path.exists() and run.stage != "done":
        print(f"resuming {folder.path} at {run.stage} step {run.step}")
    return folder, run
