"""Reliability of the TELS recipe, part 2: killed runs resume bitwise, and runs are deterministic.

Every run here is a real ``recipes/tels_offline.py`` process on CPU with one
thread (``OMP_NUM_THREADS=1``, ``threads=1``), the paper's values at the ``smoke`` budget, shrunk to
a few seconds of work. A resumed run must reproduce the uninterrupted run
bitwise: same ``results.json`` (every evaluation return, the final score, the
β selection losses), same TS-IDM weights, same logged losses.

Runs, kills and faults at an exact point come from ``tests/recipe_process.py``.
"""
from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.recipe_process import assert_same_run, assert_same_tsidm, csv_log, kill_when, outcome, recipe_env, run
from torchrl_tels.modules import TSIDM
from torchrl_tels.training import load_training_state

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run: the results every interrupted run must reproduce."""
    run_dir = tmp_path_factory.mktemp("reference") / "run"
    run(run_dir)
    return run_dir


# --------------------------------------------------------------------------- tests
def test_same_seed_same_results_and_wandb_failure_is_harmless(reference, tmp_path):
    """Determinism end to end: a second run with the same seed, whose wandb
    (online, no login, no reachable server) fails, gives identical TS-IDM losses (every logged
    term, both β), identical evaluation returns and identical weights, from its CSV log."""
    env = recipe_env(HOME=str(tmp_path / "home"), WANDB_BASE_URL="http://127.0.0.1:9")
    env.pop("WANDB_API_KEY", None)
    env.pop("WANDB_MODE", None)
    proc = run(tmp_path / "run", "logger.wandb_mode=online", env=env)
    assert proc.stderr.count("wandb is off for this run") == 1, proc.stderr[-2000:]
    assert_same_run(tmp_path / "run", reference)
    tsidm_terms = [name for name in csv_log(reference) if "/tsidm/ell_" in name]
    assert len(tsidm_terms) == 6 and all(len(csv_log(reference)[name]) == 20 for name in tsidm_terms)
    assert len(outcome(reference)["evaluations"]) == 4
    # beta=auto compares the unweighted sum (tsidm.beta_selection's default); at beta=1 it is Eq. (7).
    by_beta = {r["beta"]: r for r in outcome(reference)["beta_results"]}
    assert sorted(by_beta) == [0.1, 1.0]
    assert by_beta[1.0]["final_sum"] == pytest.approx(by_beta[1.0]["final_loss"], rel=1e-6)
    assert by_beta[0.1]["final_loss"] < by_beta[0.1]["final_sum"]
    assert outcome(reference)["beta"] == min(by_beta, key=lambda b: by_beta[b]["final_sum"])


def test_sigkill_in_stage2_then_resume(reference, tmp_path):
    run_dir = tmp_path / "run"
    # Kill a little after the first stage-2 checkpoint that follows an evaluation (step 50),
    # so that the steps after it are lost and must be redone identically.
    seen = kill_when(run_dir, lambda s: s["stage"] == "policy" and s["step"] >= 72, delay=0.1)
    at_kill = load_training_state(run_dir / "state.pt")
    assert at_kill["stage"] == "policy" and 72 <= at_kill["step"] < 200, (seen["step"], at_kill["step"])
    assert [e["step"] for e in at_kill["evaluations"]][:1] == [50]  # evaluations travel in the checkpoint
    assert not (run_dir / "results.json").exists()
    proc = run(run_dir, "resume=true")
    assert f"resuming {run_dir} at policy step {at_kill['step']}" in proc.stdout
    assert_same_run(run_dir, reference)


def test_sigkill_in_stage1_then_resume(reference, tmp_path):
    run_dir = tmp_path / "run"
    # During the second β candidate, after its first checkpoint: the first candidate is done
    # (its model in best_tsidm.pt), the second must continue from step 24 or later.
    kill_when(run_dir, lambda s: s["stage"] == "tsidm" and s.get("candidate") == 1 and s["step"] >= 24, delay=0.1)
    at_kill = load_training_state(run_dir / "state.pt")
    assert at_kill["stage"] == "tsidm" and at_kill["candidate"] == 1 and at_kill["step"] >= 24
    assert not (run_dir / "tsidm.pt").exists()
    proc = run(run_dir, "resume=true")
    assert f"resuming {run_dir} at tsidm step {at_kill['step']}" in proc.stdout
    assert_same_run(run_dir, reference)


def test_sigkill_at_exact_checkpoints_then_resume(reference, tmp_path, driver):
    """One run killed three times, each right after a given checkpoint, resumed each time:

    * between the two β candidates (candidate 1 at step 0: nothing of it saved yet);
    * candidate 1 at step 96, inside the last 10% of steps whose losses select β;
    * between the stages (stage 2 at step 0): the resumed run loads tsidm.pt and
      must build the same stage-2 networks as a run that trained stage 1 itself.
    """
    run_dir = tmp_path / "run"
    for at, resuming in [("tsidm,1,0", None), ("tsidm,1,96", "tsidm step 0"), ("policy,0,0", "tsidm step 96")]:
        extra = ["resume=true"] if resuming else []
        proc = run(run_dir, *extra, driver=(driver, "kill_after_checkpoint", at), check=False)
        assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
        if resuming:
            assert f"resuming {run_dir} at {resuming}" in proc.stdout
        state = load_training_state(run_dir / "state.pt")
        assert f"{state['stage']},{state.get('candidate')},{state['step']}" == at
    proc = run(run_dir, "resume=true")
    assert f"resuming {run_dir} at policy step 0" in proc.stdout
    assert_same_run(run_dir, reference)
    # resume=true on a finished run changes nothing
    before = (run_dir / "results.json").read_bytes()
    proc = run(run_dir, "resume=true")
    assert "already finished; nothing to resume" in proc.stdout
    assert (run_dir / "results.json").read_bytes() == before


def test_sigkill_in_stage2_of_a_pretrained_tsidm_run_then_resume(reference, tmp_path, driver):
    """A run that starts from ``tsidm.checkpoint`` checkpoints as stage 2, so a kill there resumes in
    stage 2 at its step, and equals the uninterrupted run from the same checkpoint."""
    pretrained = [f"tsidm.checkpoint={reference / 'tsidm.pt'}"]
    run(tmp_path / "whole", *pretrained)
    killed = run(tmp_path / "run", *pretrained, driver=(driver, "kill_after_checkpoint", "policy,0,96"), check=False)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    proc = run(tmp_path / "run", *pretrained, "resume=true")
    assert f"resuming {tmp_path / 'run'} at policy step 96" in proc.stdout
    assert outcome(tmp_path / "run") == outcome(tmp_path / "whole")
    assert csv_log(tmp_path / "run") == csv_log(tmp_path / "whole")
    # The run folder holds the TS-IDM it acted with, as a trained run's does, and names where it came from.
    assert_same_tsidm(tmp_path / "whole" / "tsidm.pt", reference / "tsidm.pt")
    saved = TSIDM.load(tmp_path / "whole" / "tsidm.pt")
    assert saved.metadata["checkpoint"] == str(reference / "tsidm.pt")


def test_checkpoint_counts_the_time_spent_so_far(tmp_path):
    """A checkpoint written inside a timed span holds the time up to that moment, so a run killed
    before the span ends keeps it; nested spans both count."""
    from torchrl_tels.trainer import RunState

    run = RunState(config={})
    with run.time("policy_s"):
        time.sleep(0.05)
        with run.time("eval_s"):
            time.sleep(0.05)
            run.save(tmp_path / "state.pt")
    saved = load_training_state(tmp_path / "state.pt")["wall"]
    assert saved["policy_s"] >= 0.1 and 0.05 <= saved["eval_s"] < saved["policy_s"]
    assert run.wall["policy_s"] >= saved["policy_s"] and run._clocks == []
