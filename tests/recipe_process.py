"""Real ``recipes/tels_offline.py`` processes for the reliability tests: runs, kills at a chosen
checkpoint, faults injected by a driver, and bitwise comparison of two runs' outcomes.

Faults that must land at an exact point (a kill right after a given checkpoint, a NaN in a given loss
term at a given step) are injected by ``DRIVER``, a small script that patches one library function and
then runs the unchanged recipe with ``runpy``; the recipe itself has no test hooks.
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


def recipe_env(**extra: str) -> dict[str, str]:
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
    proc = subprocess.run(_command(run_dir, *overrides, driver=driver, base=base), cwd=REPO_ROOT, env=env or recipe_env(),
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
        proc = subprocess.Popen(_command(run_dir), cwd=REPO_ROOT, env=recipe_env(), stdout=log, stderr=subprocess.STDOUT)
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
