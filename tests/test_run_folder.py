"""One run, one folder: no run writes into another's ``run_dir``, in series, at once, or in a sweep."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from torchrl_tels.errors import CheckpointError, ConfigError
from torchrl_tels.run_folder import check_run_dir_free, claim_run_dir, LOCK_NAME, RunFolder

REPO_ROOT = Path(__file__).resolve().parents[1]
RECIPE = REPO_ROOT / "recipes" / "tels_offline.py"
# A run of a few seconds: every stage, the monitor and the final evaluation, with tiny budgets.
TINY = ["budget=smoke", "threads=1", "tsidm.steps=5", "policy.steps=20", "eval.interval=20", "eval.episodes=1",
        "eval.max_steps=10", "monitor.steps=5", "checkpoint.interval=10", "logger.log_interval=10"]


def start(*overrides: str, cwd: Path = REPO_ROOT, multirun: bool = False) -> subprocess.Popen:
    flags = ["-m"] if multirun else []
    return subprocess.Popen([sys.executable, str(RECIPE), *flags, *TINY, *overrides], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(proc: subprocess.Popen) -> tuple[int, str]:
    _, err = proc.communicate(timeout=600)
    return proc.returncode, err


def run_seed(run_dir: Path) -> int:
    return yaml.safe_load((run_dir / "config.yaml").read_text())["seed"]


def test_claim_is_exclusive_and_released(tmp_path):
    folder = tmp_path / "run"
    first = claim_run_dir(folder, resume=False, overwrite=False)
    with pytest.raises(ConfigError, match="in use by another running job"):
        claim_run_dir(folder, resume=True, overwrite=False)  # even a resume waits for the live run
    first.release()
    (folder / "results.json").write_text("{}")
    with pytest.raises(ConfigError, match="resume=true.*new run_dir.*overwrite=true"):
        check_run_dir_free(folder, resume=False, overwrite=False)
    with pytest.raises(ConfigError, match="results.json"):
        claim_run_dir(folder, resume=False, overwrite=False)
    with claim_run_dir(folder, resume=True, overwrite=False):
        assert (folder / "results.json").exists()  # a resume keeps the run's records
    (folder / "config.yaml").write_text("seed: 1\n")
    (folder / "seed0").mkdir()
    (folder / "seed0" / "results.json").write_text("{}")
    with claim_run_dir(folder, resume=False, overwrite=True):
        assert [p.name for p in folder.iterdir()] == [LOCK_NAME]  # nothing of the old run mixes with the new one
    stranger = tmp_path / "project"
    stranger.mkdir()
    (stranger / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="holds files but no run"):
        claim_run_dir(stranger, resume=False, overwrite=True)  # overwrite deletes only a run's folder
    assert (stranger / "notes.txt").read_text() == "mine"
    check_run_dir_free(tmp_path / "empty", resume=False, overwrite=False)  # absent: free
    (tmp_path / "empty").mkdir()
    check_run_dir_free(tmp_path / "empty", resume=False, overwrite=False)  # empty (as a sweep job's): free
    assert [p.name for p in folder.iterdir()] == [LOCK_NAME]


def test_run_folder_reads_back_what_a_run_writes(tmp_path):
    stacked = RunFolder(tmp_path / "stacked")
    for seed in (0, 1):
        stacked.seed(seed).write_config(f"seed: {seed}\n")
    stacked.write_config("seeds: [0, 1]\n")
    single = RunFolder(tmp_path / "single")
    single.write_config("seed: 3\n")
    # a run of several seeds counts as its seeds' folders, not as the folder that aggregates them
    assert RunFolder.find(tmp_path) == [single, stacked.seed(0), stacked.seed(1)]
    assert stacked.seed_folders() == [stacked.seed(0), stacked.seed(1)]
    assert [f.status() for f in RunFolder.find(tmp_path)] == ["unfinished"] * 3
    with single.claim(resume=True, overwrite=False):
        assert single.status() == "running"
    with pytest.raises(CheckpointError, match="has no results.json.*then export"):
        RunFolder.open_finished(single.path, purpose="export")
    single.write_results({"seed": 3, "dataset": "d"})
    assert single.status() == "finished"
    with pytest.raises(CheckpointError, match="without policy.pt, tsidm.pt"):
        RunFolder.open_finished(single.path, required=(RunFolder.POLICY, RunFolder.TSIDM))
    opened = RunFolder.open_finished(single.path)
    assert opened.read_results() == {"seed": 3, "dataset": "d"} and opened.read_config() == {"seed": 3}
    assert json.loads((tmp_path / "single" / "results.json").read_text())["seed"] == 3


def test_resume_and_overwrite_must_be_booleans():
    from benchmarks.harness import recipe_config
    from torchrl_tels.config import validate_config

    with pytest.raises(ConfigError, match="overwrite must be true or false, got 'flase'"):
        validate_config(recipe_config(["overwrite=flase"]))


def test_two_runs_started_at_once_on_one_run_dir(tmp_path):
    run_dir = tmp_path / "shared"
    procs = [start(f"run_dir={run_dir}", f"seed={seed}") for seed in (1, 2)]
    outcomes = [finish(p) for p in procs]
    codes = sorted(code for code, _ in outcomes)
    assert codes == [0, 2], [err[-2000:] for _, err in outcomes]
    winner = 1 if outcomes[0][0] == 0 else 2
    loser_err = next(err for code, err in outcomes if code == 2)
    assert f"run_dir {run_dir}" in loser_err and "error:" in loser_err
    assert run_seed(run_dir) == winner
    assert json.loads((run_dir / "results.json").read_text())["seed"] == winner


def test_second_fresh_run_into_a_finished_one_is_refused(tmp_path):
    run_dir = tmp_path / "a"
    code, err = finish(start(f"run_dir={run_dir}", "seed=1"))
    assert code == 0, err[-2000:]
    before = {p.name: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    code, err = finish(start(f"run_dir={run_dir}", "seed=2"))
    assert code == 2
    assert err.strip().splitlines()[-1].startswith(f"error: run_dir {run_dir} already holds another run's files")
    assert {p.name: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before  # untouched
    code, err = finish(start(f"run_dir={run_dir}", "seed=2", "overwrite=true"))
    assert code == 0, err[-2000:]
    assert json.loads((run_dir / "results.json").read_text())["seed"] == 2


def test_sweep_jobs_get_their_own_folders_and_resume(tmp_path):
    sweep = tmp_path / "sweep"
    launch = tmp_path / "launch"  # where the user stands: nothing of the sweep's may land here
    launch.mkdir()
    code, err = finish(start("seed=1,2", f"hydra.sweep.dir={sweep}", cwd=launch, multirun=True))
    assert code == 0, err[-2000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    # named by job number and overrides: hydra's override_dirname, sorted by key
    assert [p.name.split(",")[0] for p in jobs] == ["0_budget=smoke", "1_budget=smoke"]
    assert ["seed=1" in jobs[0].name.split(","), "seed=2" in jobs[1].name.split(",")] == [True, True]
    for job, seed in zip(jobs, (1, 2)):
        assert json.loads((job / "results.json").read_text())["seed"] == seed
    assert (sweep / "multirun.yaml").exists() and not any(launch.iterdir())
    # The same command with resume=true finds each job's folder and skips the finished ones.
    stamps = [(job / "results.json").stat().st_mtime_ns for job in jobs]
    proc = start("seed=1,2", f"hydra.sweep.dir={sweep}", "resume=true", cwd=launch, multirun=True)
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-2000:]
    assert out.count("already finished; nothing to resume") == 2
    assert [(job / "results.json").stat().st_mtime_ns for job in jobs] == stamps
    assert sorted(p for p in sweep.iterdir() if p.is_dir()) == jobs  # resume=true is not in the names


def test_sweep_through_the_local_submitit_launcher(tmp_path):
    """hydra/launcher=local: the cluster launcher's code path, each job a process of its own."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "sweep"
    code, err = finish(start("hydra/launcher=local", "seed=1,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path,
                             multirun=True))
    assert code == 0, err[-2000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name.split("_")[0] for p in jobs] == ["0", "1"]
    assert [json.loads((job / "results.json").read_text())["seed"] for job in jobs] == [1, 2]
    # submitit ran each job apart: one folder of logs per job
    assert len([p for p in (sweep / ".submitit").iterdir() if p.name.isdigit()]) == 2
    # ... and the summary command turns the sweep into its table
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "summarize.py"), str(sweep)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    scores = [json.loads((job / "results.json").read_text())["final_normalized_score_mean"] for job in jobs]
    row = next(line for line in (sweep / "summary.md").read_text().splitlines() if line.startswith("| hopper"))
    assert row.split("|")[2].strip() == f"{sum(scores) / 2:.1f}" and row.split("|")[4].strip() == "2"
