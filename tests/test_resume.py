"""Reliability of the TELS recipe, part 2: killed runs resume bitwise, and runs are deterministic.

Every run here is a real ``recipes/tels_offline.py`` process on CPU with one
thread (``OMP_NUM_THREADS=1``, ``threads=1``), the paper's values at the ``smoke`` budget, shrunk to
a few seconds of work. A resumed run must reproduce the uninterrupted run
bitwise: same ``results.json`` (every evaluation return, the final score, the
β selection losses), same TS-IDM weights, same logged losses.

Faults that must land at an exact point (a kill right after a given
checkpoint, a NaN in a given loss term at a given step) are injected by a
small driver that patches one library function and then runs the unchanged
recipe with ``runpy``; the recipe itself has no test hooks.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchrl_tels.training import load_training_state

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[1]
RECIPE = REPO_ROOT / "recipes" / "tels_offline.py"
# Stage 1: two β candidates x 100 steps; stage 2: 200 steps; a checkpoint every 24
# steps of either stage (so one, at 96, falls in the last 10% of stage 1 whose
# losses pick β), an evaluation every 50 policy steps. About 10 s a run.
COMMON = ["domain=paper", "budget=smoke", "threads=1", "seed=3", "checkpoint.interval=24", "logger.log_interval=10",
          "eval.episodes=1", "eval.last_n=2", "eval.max_steps=50"]
RUN = [*COMMON, "tsidm.beta=auto", "tsidm.beta_candidates=[0.1,1.0]", "tsidm.steps=100",
       "policy.steps=200", "eval.interval=50"]
# For the NaN tests: one β, 20 TS-IDM steps, 100 policy steps, no evaluation before the end.
FAST = [*COMMON, "tsidm.beta=1.0", "tsidm.steps=20", "policy.steps=100", "eval.interval=100"]
# Wall-clock entries differ from run to run; everything else must match bitwise.
NOT_COMPARED = ("wall_time_s", "steps_per_s")

DRIVER = '''
"""Runs the recipe with one fault injected: driver.py RECIPE MODE AT [overrides...]."""
import os, runpy, signal, sys
import torch
import torchrl_tels.objectives as objectives
import torchrl_tels.training as training

recipe, mode, at = sys.argv[1], sys.argv[2], sys.argv[3]
calls = [0]
if mode == "kill_after_checkpoint":  # SIGKILL right after state.pt is written at `at` = "stage,candidate,step"
    save = training.save_training_state
    def save_then_die(path, state):
        save(path, state)
        if f"{state.get('stage')},{state.get('candidate')},{state.get('step')}" == at:
            os.kill(os.getpid(), signal.SIGKILL)
    training.save_training_state = save_then_die
elif mode == "nan_loss":  # the value loss (Eq. 8) becomes NaN at stage-2 step `at`
    forward = objectives.LatentExpectileLoss.forward
    def nan_loss(self, tensordict):
        out = forward(self, tensordict)
        calls[0] += 1
        if calls[0] == int(at) + 1:
            out.set("loss_value", out.get("loss_value") * float("nan"))
        return out
    objectives.LatentExpectileLoss.forward = nan_loss
elif mode == "inf_grad":  # at stage-2 step `at` the guide loss stays finite but its gradient is inf
    forward = objectives.TSymGuideLoss.forward
    def inf_grad(self, tensordict):
        out = forward(self, tensordict)
        calls[0] += 1
        if calls[0] == int(at) + 1:
            weight = next(p for p in self.parameters() if p.requires_grad)
            key = next(k for k in out.keys() if k.startswith("loss_"))
            out.set(key, out.get(key) + torch.sqrt(weight - weight.detach()).sum())  # + 0, d/dw = inf
        return out
    objectives.TSymGuideLoss.forward = inf_grad
elif mode == "nan_reward":  # the batch of stage-2 step `at` carries a NaN reward: Eq. (8)'s target is NaN
    from torchrl.data import TensorDictReplayBuffer
    sample = TensorDictReplayBuffer.sample
    def nan_sample(self, *args, **kwargs):
        batch = sample(self, *args, **kwargs)
        if "latent" in batch.keys():  # stage 2's buffer holds the encoded data
            calls[0] += 1
            if calls[0] == int(at) + 1:
                batch.set(("next", "reward"), batch.get(("next", "reward")) * float("nan"))
        return batch
    TensorDictReplayBuffer.sample = nan_sample
else:
    raise SystemExit(f"unknown mode {mode}")
sys.argv = [recipe, *sys.argv[4:]]
runpy.run_path(recipe, run_name="__main__")
'''


# --------------------------------------------------------------------------- helpers
def _env(**extra: str) -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", **extra}
    env.pop("HYDRA_FULL_ERROR", None)
    return env


def _command(run_dir: Path, *overrides: str, driver: tuple[Path, str, str] | None = None,
             base: list[str] = RUN) -> list[str]:
    args = [*base, f"run_dir={run_dir}", *overrides]
    if driver is None:
        return [sys.executable, str(RECIPE), *args]
    path, mode, step = driver
    return [sys.executable, str(path), str(RECIPE), mode, str(step), *args]


def run(run_dir: Path, *overrides: str, driver=None, env=None, check=True, base=RUN) -> subprocess.CompletedProcess:
    proc = subprocess.run(_command(run_dir, *overrides, driver=driver, base=base), cwd=REPO_ROOT, env=env or _env(),
                          capture_output=True, text=True, timeout=300)
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def kill_when(run_dir: Path, reached, delay: float) -> dict:
    """Starts a run, waits until its state.pt satisfies ``reached``, waits ``delay`` s more, SIGKILLs it.

    Returns the state seen. state.pt is replaced atomically, so reading it
    while the run writes always gives a whole file.
    """
    with open(run_dir.parent / f"{run_dir.name}.log", "w") as log:
        proc = subprocess.Popen(_command(run_dir), cwd=REPO_ROOT, env=_env(), stdout=log, stderr=subprocess.STDOUT)
        try:
            path, seen, deadline = run_dir / "state.pt", None, time.monotonic() + 240
            while time.monotonic() < deadline:
                assert proc.poll() is None, "the run ended before it could be killed"
                stamp = path.stat().st_mtime_ns if path.exists() else None
                if stamp is not None and stamp != seen:
                    seen, state = stamp, load_training_state(path)
                    if reached(state):
                        time.sleep(delay)
                        proc.send_signal(signal.SIGKILL)
                        assert proc.wait() == -signal.SIGKILL
                        return state
                time.sleep(0.01)
            pytest.fail("the run never reached the point to kill it at")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def outcome(run_dir: Path) -> dict:
    results = json.loads((run_dir / "results.json").read_text())
    return {key: value for key, value in results.items() if key not in NOT_COMPARED}


def csv_log(run_dir: Path) -> dict[str, dict[int, str]]:
    """Every logged scalar, by file and step. A step logged twice (work redone after a
    kill) must have logged the same value both times."""
    log = {}
    for path in sorted((run_dir / "csv" / "scalars").rglob("*.csv")):
        rows = {}
        for line in path.read_text().splitlines():
            step, value = line.split(",")
            assert rows.setdefault(int(step), value) == value, f"{path.name} step {step}: {rows[int(step)]} != {value}"
            rows[int(step)] = value
        log[str(path.relative_to(run_dir))] = rows
    return log


def assert_same_tsidm(a: Path, b: Path) -> None:
    sa = torch.load(a, weights_only=True)["state_dict"]
    sb = torch.load(b, weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys()
    for key in sa:
        assert torch.equal(sa[key], sb[key]), key


def assert_same_run(resumed: Path, reference: Path) -> None:
    assert outcome(resumed) == outcome(reference)
    assert_same_tsidm(resumed / "tsidm.pt", reference / "tsidm.pt")
    assert csv_log(resumed) == csv_log(reference)
    assert load_training_state(resumed / "state.pt")["stage"] == "done"


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted run: the results every interrupted run must reproduce."""
    run_dir = tmp_path_factory.mktemp("reference") / "run"
    run(run_dir)
    return run_dir


@pytest.fixture
def driver(tmp_path) -> Path:
    path = tmp_path / "driver.py"
    path.write_text(DRIVER)
    return path


# --------------------------------------------------------------------------- tests
def test_same_seed_same_results_and_wandb_failure_is_harmless(reference, tmp_path):
    """Determinism end to end: a second run with the same seed, whose wandb
    (online, no login, no reachable server) fails, gives identical TS-IDM losses (every logged
    term, both β), identical evaluation returns and identical weights, from its CSV log."""
    env = _env(HOME=str(tmp_path / "home"), WANDB_BASE_URL="http://127.0.0.1:9")
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
