"""Reliability of the TELS recipe, part 3: a run stops at a non-finite loss or weight, eager and compiled,
and a compiled run resumes bitwise.

Real ``recipes/tels_offline.py`` processes, faults injected at an exact step by the driver of
``tests/recipe_process.py`` (which patches one library function and runs the unchanged recipe).
"""
from __future__ import annotations

import signal

import pytest
import torch

from tests.recipe_process import FAST, assert_same_run, run
from torchrl_tels.training import load_training_state

pytestmark = pytest.mark.slow


def test_nan_loss_stops_run_and_keeps_last_good_checkpoint(tmp_path, driver):
    run_dir = tmp_path / "run"
    proc = run(run_dir, base=FAST, driver=(driver, "nan_loss", "60"), check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: stage 2 (value): loss_value became nan at step 60; the run stops here "
        "and the last good checkpoint is kept unchanged."
    )
    state = load_training_state(run_dir / "state.pt")  # loading also proves the file is whole
    assert (state["stage"], state["step"]) == ("policy", 48)
    assert not (run_dir / "results.json").exists()


def test_compiled_run_stops_at_a_nan_loss_naming_term_and_step(tmp_path, driver):
    """With compile.compile=true the NaN stop still names the term and the step: the watch reads
    the compiled step's outputs. The NaN comes from the data, as the compiled step sees it."""
    run_dir = tmp_path / "run"
    proc = run(run_dir, "compile.compile=true", base=FAST, driver=(driver, "nan_reward", "60"), check=False)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: stage 2 (value): loss_value became nan at step 60; the run stops here "
        "and the last good checkpoint is kept unchanged."
    )
    assert (load_training_state(run_dir / "state.pt")["step"]) == 48


def test_compiled_run_killed_then_resumed_matches_an_uninterrupted_one(tmp_path, driver):
    """compile.compile=true: a run killed right after its stage-2 checkpoint at step 48 and resumed
    (compiling afresh) ends exactly as the same compiled run uninterrupted."""
    reference_dir, run_dir = tmp_path / "reference", tmp_path / "run"
    run(reference_dir, "compile.compile=true", base=FAST)
    proc = run(run_dir, "compile.compile=true", base=FAST, driver=(driver, "kill_after_checkpoint", "policy,0,48"),
               check=False)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    proc = run(run_dir, "compile.compile=true", "resume=true", base=FAST)
    assert f"resuming {run_dir} at policy step 48" in proc.stdout
    assert_same_run(run_dir, reference_dir)


def test_non_finite_weights_are_never_checkpointed(tmp_path, driver):
    """A finite loss with an infinite gradient at step 71 turns the guide weights to NaN in the
    optimizer step; the checkpoint due right after it (step 72) is refused and the one at 48 kept."""
    run_dir = tmp_path / "run"
    proc = run(run_dir, base=FAST, driver=(driver, "inf_grad", "71"), check=False)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: checkpoint state.pt: modules.guide_loss.") and last.endswith(
        "holds NaN or inf; it is not written and the last good checkpoint is kept."
    ), proc.stderr[-2000:]
    state = load_training_state(run_dir / "state.pt")
    assert (state["stage"], state["step"]) == ("policy", 48)
    for name in ("value_loss", "guide_loss"):
        assert all(torch.isfinite(t).all() for t in state["modules"][name].values() if t.is_floating_point())
