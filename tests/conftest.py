from __future__ import annotations

import importlib.resources
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.recipe_process import DRIVER, RECIPE, REPO_ROOT
from torchrl_tels.data import embedded_dataset_path


@pytest.fixture
def hopper_arrays():
    with importlib.resources.as_file(embedded_dataset_path("hopper-medium-v2-10k")) as path, np.load(path) as data:
        return {key: data[key] for key in data.files}


def pytest_configure(config):
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if not worker:
        return
    # Each xdist worker runs on its own share of the CPUs, so the recipe processes it starts see only that
    # share: their threads=auto and monitor.background=auto then keep to it instead of starting a second
    # thread or a background monitor process on a core another worker is using.
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if hasattr(os, "sched_setaffinity") and workers <= len(cpus := sorted(os.sched_getaffinity(0))):
        os.sched_setaffinity(0, cpus[int(worker.removeprefix("gw")) % workers::workers])
    # One torch thread per worker: the workers already fill the cores, and torch's default
    # threads thrash when another process is busy.
    torch.set_num_threads(1)


@pytest.fixture
def driver(tmp_path) -> Path:
    """``tests/recipe_process.DRIVER`` written out: runs the recipe with one fault injected."""
    path = tmp_path / "driver.py"
    path.write_text(DRIVER)
    return path


@pytest.fixture(autouse=True)
def _threads():
    """Each test ends on the thread count it started with. A torchrl batched env raises torch's thread count
    process-wide when it closes (by its number of workers, up to the count at torchrl's import): that left an
    xdist worker on two threads on its one core for every later test, many times slower."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture(scope="session")
def finished_recipe_run(tmp_path_factory):
    """A short recipe run on the paper's settings, for the study's readings of finished runs (``study``).

    Two evaluation episodes: the batched (vector-env) evaluation runs between the value updates."""
    run_dir = tmp_path_factory.mktemp("finished_recipe_run") / "run"
    overrides = ["domain=paper", "budget=smoke", "threads=1", "seed=2", "tsidm.beta=1.0", "tsidm.steps=20",
                 "policy.steps=120", "eval.interval=60", "eval.episodes=2", "eval.max_steps=30",
                 "logger.log_interval=10", f"run_dir={run_dir}"]
    proc = subprocess.run([sys.executable, str(RECIPE), *overrides], cwd=REPO_ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir
