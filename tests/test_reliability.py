"""Reliability of the TELS recipe and its files, part 1: bad input, checkpoint safety, wandb.

Each bad input ends the run with exit code 2 and one line ``error: <message>``
on stderr (no traceback), and writes no checkpoint, result or half file. Most
cases call the recipe's hydra entry point in this process (the same code the
command line runs, without paying for a new interpreter per case); the
``test_cli_*`` tests run the real command line for the output format and for
the two cases hydra handles before the recipe's code runs.

Kills, resumption, determinism and NaN handling are in ``test_resume.py``.
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import pickle
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_tels.checkpoint import atomic_save, CheckpointError, load_checkpoint
import torchrl_tels.config as config_module
from torchrl_tels.config import ConfigError, training_config, validate_config
from torchrl_tels.data import embedded_dataset_path
from torchrl_tels.modules import TSIDM
from torchrl_tels.record import RunLogger
from torchrl_tels.errors import TelsError
from torchrl_tels.training import write_json, write_text
from torchrl_tels.training import (
    NonFiniteLossError,
    is_user_error,
    load_training_state,
    save_training_state,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
RECIPE = REPO_ROOT / "recipes" / "tels_offline.py"
CONFIG_DIR = REPO_ROOT / "recipes" / "config"
SMALL = ["tsidm.steps=2", "policy.steps=2", "eval.max_steps=5"]


# --------------------------------------------------------------------------- helpers
@pytest.fixture(scope="module")
def recipe():
    spec = importlib.util.spec_from_file_location("tels_offline_recipe", RECIPE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def no_minari_download(monkeypatch):
    """An unknown dataset id must never reach the network, whatever is installed."""
    import torchrl_tels.data.datasets as datasets

    monkeypatch.setattr(datasets, "_minari_remote_support", lambda: "downloads are off in tests")


def compose_cfg(*overrides: str):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("config", overrides=["domain=paper", "budget=smoke", *overrides])


def _files(folder: Path) -> dict[str, bytes]:
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def expect_error(recipe, capsys, run_dir: Path, *overrides: str) -> str:
    """Runs the recipe's entry point, checks it ends with one ``error:`` line and wrote nothing.

    Returns the message. Files present in ``run_dir`` before (a checkpoint under
    test) must be left byte for byte, and no file may be added: a refused start
    is refused before the run folder, its config or its logs are created.
    """
    cfg = compose_cfg(f"run_dir={run_dir}", *SMALL, *overrides)
    before = _files(run_dir)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        recipe.main.__wrapped__(cfg)  # the function @hydra.main wraps: the CLI's code path
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    after = _files(run_dir)
    assert {name: after[name] for name in before} == before, "an existing file was changed"
    assert set(after) == set(before), sorted(set(after) - set(before))
    if not before:
        assert not run_dir.exists() or not any(run_dir.iterdir()), sorted(p.name for p in run_dir.iterdir())
    return lines[0][len("error: "):]


def hopper_arrays(rows: int = 2000) -> dict[str, np.ndarray]:
    with embedded_dataset_path().open("rb") as f, np.load(f) as data:
        return {key: np.array(data[key][:rows]) for key in data.files}


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    np.savez(path, **arrays)
    return path


def small_tsidm(obs_dim: int, act_dim: int) -> TSIDM:
    cells = [16, 16]
    return TSIDM(obs_dim, act_dim, encoder_cells=cells, decoder_cells=cells, inverse_cells=cells,
                 action_decoder_cells=cells, dynamics_cells=cells)


class _Payload:
    """Unpickling this runs ``os.makedirs(marker)``: code execution, as a hostile checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.makedirs, (str(self.marker),)


# ------------------------------------------------------------ bad data (catalogue)
@pytest.mark.parametrize("obs_dim,act_dim,sizes", [(5, 3, "5/3"), (11, 2, "11/2")], ids=["observation", "action"])
def test_dimension_mismatch_between_data_and_env(recipe, capsys, tmp_path, obs_dim, act_dim, sizes):
    arrays = hopper_arrays()
    arrays["observations"] = arrays["observations"][:, :obs_dim]
    arrays["next_observations"] = arrays["next_observations"][:, :obs_dim]
    arrays["actions"] = arrays["actions"][:, :act_dim]
    path = write_npz(tmp_path / "data.npz", arrays)
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert f"observation/action sizes {sizes} but env Hopper-v4 has 11/3" in message


@pytest.mark.parametrize("key,value", [("observations", np.nan), ("actions", np.inf), ("rewards", np.nan)])
def test_non_finite_values_in_data(recipe, capsys, tmp_path, key, value):
    arrays = hopper_arrays()
    arrays[key] = arrays[key].copy()
    arrays[key][7] = value
    path = write_npz(tmp_path / "data.npz", arrays)
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert f"'{key}' has" in message and "NaN/inf value(s) (first at row 7)" in message


def test_empty_dataset(recipe, capsys, tmp_path):
    path = write_npz(tmp_path / "data.npz", hopper_arrays(rows=0))
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert "the dataset is empty (0 transitions)" in message


def test_dataset_smaller_than_batch(recipe, capsys, tmp_path):
    path = write_npz(tmp_path / "data.npz", hopper_arrays(rows=100))
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert "has 100 transitions, fewer than tsidm.batch_size=256" in message


def test_missing_keys(recipe, capsys, tmp_path):
    arrays = hopper_arrays()
    del arrays["rewards"]
    path = write_npz(tmp_path / "data.npz", arrays)
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert "missing key(s) ['rewards']" in message


def test_unknown_dataset_id(recipe, capsys, tmp_path, no_minari_download):
    message = expect_error(recipe, capsys, tmp_path / "run", "dataset.name=no-such-dataset-v0")
    assert message.startswith("Unknown dataset 'no-such-dataset-v0'. Looked for:")


def test_unknown_task(recipe, capsys, tmp_path):
    message = expect_error(recipe, capsys, tmp_path / "run", "dataset.task=no-such-task")
    assert message.startswith("Unknown task 'no-such-task'.")


def test_subset_larger_than_dataset(recipe, capsys, tmp_path):
    message = expect_error(recipe, capsys, tmp_path / "run", "dataset.size=100000")
    assert "size must be in (0, 9013]" in message


# ------------------------------------------------------------- bad checkpoints
def test_checkpoint_older_than_an_option_resumes_only_where_it_behaved_the_same():
    """A checkpoint written before tsidm.beta_selection existed: with a fixed beta the option has
    no effect, so the run continues; with beta=auto it selected by Eq. (7) itself ("weighted"),
    so it continues only under that reading."""
    def older(*overrides):
        saved = training_config(compose_cfg("run_dir=x", *overrides))
        del saved["tsidm"]["beta_selection"]
        return saved

    current = training_config(compose_cfg("run_dir=x"))
    config_module.check_same_run(older(), current, "state.pt")
    auto = training_config(compose_cfg("run_dir=x", "tsidm.beta=auto"))
    with pytest.raises(ConfigError, match=r"tsidm.beta_selection: 'weighted' -> 'unweighted'"):
        config_module.check_same_run(older("tsidm.beta=auto"), auto, "state.pt")
    weighted = training_config(compose_cfg("run_dir=x", "tsidm.beta=auto", "tsidm.beta_selection=weighted"))
    config_module.check_same_run(older("tsidm.beta=auto"), weighted, "state.pt")
    with pytest.raises(ConfigError, match=r"tsidm.beta: 1.0 -> 0.5"):  # other keys are still compared
        config_module.check_same_run(older(), training_config(compose_cfg("run_dir=x", "tsidm.beta=0.5")), "state.pt")


def test_tsidm_checkpoint_made_for_another_env(recipe, capsys, tmp_path):
    small_tsidm(17, 6).save(tmp_path / "walker_tsidm.pt")  # Walker2d sizes; the run is Hopper (11/3)
    message = expect_error(recipe, capsys, tmp_path / "run", f"tsidm.checkpoint={tmp_path / 'walker_tsidm.pt'}")
    assert "has observation_dim=17, but this environment/dataset has observation_dim=11" in message


def test_policy_checkpoint_made_for_another_env(recipe, capsys, tmp_path):
    """resume=true on a run_dir whose state.pt (policy weights, optimizers) came from a Walker2d run."""
    other = training_config(compose_cfg("run_dir=x", *SMALL, "dataset.name=walker2d-medium-v2-10k"))
    save_training_state(tmp_path / "run" / "state.pt", {"stage": "policy", "step": 50, "config": other})
    message = expect_error(recipe, capsys, tmp_path / "run", "resume=true")
    assert "state.pt was made by a run with another config" in message
    assert "dataset.name: 'walker2d-medium-v2-10k' -> 'hopper-medium-v2-10k'" in message


def test_truncated_checkpoint(recipe, capsys, tmp_path):
    small_tsidm(11, 3).save(tmp_path / "tsidm.pt")
    whole = (tmp_path / "tsidm.pt").read_bytes()
    (tmp_path / "truncated.pt").write_bytes(whole[: len(whole) // 2])
    message = expect_error(recipe, capsys, tmp_path / "run", f"tsidm.checkpoint={tmp_path / 'truncated.pt'}")
    assert message.startswith(f"cannot read checkpoint {tmp_path / 'truncated.pt'}: it is truncated, corrupted")


def test_corrupted_state_on_resume(recipe, capsys, tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "state.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    message = expect_error(recipe, capsys, tmp_path / "run", "resume=true")
    assert message.startswith(f"cannot read checkpoint {tmp_path / 'run' / 'state.pt'}: it is truncated, corrupted")


def test_hostile_pickle_is_refused_not_executed(recipe, capsys, tmp_path):
    marker = tmp_path / "code_ran"
    # The right "format" tag: only weights_only=True stands between the file and os.makedirs.
    torch.save({"format": TSIDM.CHECKPOINT_FORMAT, "config": _Payload(marker)}, tmp_path / "hostile.pt")
    message = expect_error(recipe, capsys, tmp_path / "run", f"tsidm.checkpoint={tmp_path / 'hostile.pt'}")
    assert "not a torchrl_tels checkpoint (UnpicklingError" in message
    assert not marker.exists()
    torch.load(tmp_path / "hostile.pt", weights_only=False)  # the file really is hostile:
    assert marker.exists()  # a plain torch.load would have run its code


def test_file_that_is_not_ours(recipe, capsys, tmp_path):
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    message = expect_error(recipe, capsys, tmp_path / "run", f"tsidm.checkpoint={tmp_path / 'foreign.pt'}")
    assert message == f"{tmp_path / 'foreign.pt'} is not a 'torchrl_tels.tsidm/v1' checkpoint (found format None)."


def test_tsidm_file_given_as_training_state(recipe, capsys, tmp_path):
    small_tsidm(11, 3).save(tmp_path / "run" / "state.pt")
    message = expect_error(recipe, capsys, tmp_path / "run", "resume=true")
    assert "is not a 'torchrl_tels.training_state/v1' checkpoint (found format 'torchrl_tels.tsidm/v1')" in message


# --------------------------------------------------------- bad hyperparameters
HYPERPARAMETER_CASES = [
    ("tsidm.beta=-0.5", "tsidm.beta must be >= 0 or 'auto', got -0.5."),
    ("value.expectile=1.0", "value.expectile must lie in (0, 1), got 1.0."),
    ("value.expectile=0", "value.expectile must lie in (0, 1), got 0.0."),
    ("policy.batch_size=0", "policy.batch_size must be a positive integer, got 0."),
    ("tsidm.batch_size=0", "tsidm.batch_size must be a positive integer, got 0."),
    ("guide.alpha=nan", "guide.alpha must be finite, got nan."),
    ("value.lr=inf", "value.lr must be finite, got inf."),
    ("tsidm.beta_candidates=[0.1,-1]", "tsidm.beta_candidates must be finite numbers >= 0, got -1."),
    ("value.num_cells=[256,0]", "value.num_cells must be a list of positive integers"),
    ("dataset.delete_boxes=[[1,0,0,1]]", "dataset.delete_boxes: each box must be [xmin, xmax, ymin, ymax]"),
    ("dataset.delete_boxes=[[0,1,0]]", "dataset.delete_boxes: each box must be [xmin, xmax, ymin, ymax]"),
    ("dataset.delete_ratio=1.5", "dataset.delete_ratio must lie in [0, 1], got 1.5."),
    ("dataset.delete_xy=[0]", "dataset.delete_xy must be two observation column indices >= 0"),
    ("guide.reencode_proposal=3", "guide.reencode_proposal must be true or false, got 3."),
    ("+tsidm.term_weights.rec=1", "tsidm.term_weights must be null or a mapping with keys among dyn, ode, tsym"),
    ("+tsidm.term_weights.dyn=-1", "tsidm.term_weights.dyn must be >= 0, got -1."),
    ("tsidm.beta_selection=lowest", "tsidm.beta_selection must be one of ('unweighted', 'weighted'), got 'lowest'."),
    ("guide.reach_weight=-0.5", "guide.reach_weight must be >= 0, got -0.5."),
]


@pytest.mark.parametrize("override,expected", HYPERPARAMETER_CASES, ids=[case[0] for case in HYPERPARAMETER_CASES])
def test_out_of_range_hyperparameter(recipe, capsys, tmp_path, override, expected):
    extra = ["tsidm.beta=auto"] if "beta_candidates" in override else []
    message = expect_error(recipe, capsys, tmp_path / "run", override, *extra)
    assert message.startswith(expected)
    assert not (tmp_path / "run").exists()  # checked before anything is created


def test_reach_weight_refused_for_the_stochastic_guide(recipe, capsys, tmp_path):
    message = expect_error(recipe, capsys, tmp_path / "run", "guide.reach_weight=1", "guide.mode=stochastic")
    assert message.startswith("guide.reach_weight applies to the deterministic guide (Eq. 9) only")
    assert not (tmp_path / "run").exists()


def test_bf16_refused_on_a_cpu_without_native_bf16(recipe, capsys, tmp_path, monkeypatch):
    # On an AVX2-only CPU bf16 autocast is emulated: steps ran 26-37x slower than fp32 (BENCHMARKS.md).
    monkeypatch.setattr(config_module, "native_bf16_supported", lambda: False)
    message = expect_error(recipe, capsys, tmp_path / "run", "precision=bf16")
    assert message.startswith("precision=bf16 needs a CPU with native bf16 matrix multiplication")
    assert "Use precision=fp32." in message
    assert not (tmp_path / "run").exists()
    config_module.check_precision_supported("fp32")  # fp32 never depends on the CPU
    monkeypatch.setattr(config_module, "native_bf16_supported", lambda: True)
    config_module.check_precision_supported("bf16")


# ------------------------------------------------------ the real command line
def run_cli(tmp_path: Path, *overrides: str, cwd: Path = REPO_ROOT) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, str(RECIPE), "domain=paper", "budget=smoke", "threads=1", *SMALL, *overrides],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=120,
    )


def test_cli_prints_one_error_line(tmp_path):
    launch = tmp_path / "launch"
    launch.mkdir()
    proc = run_cli(tmp_path, f"run_dir={tmp_path / 'run'}", "value.expectile=1.5", cwd=launch)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == ["error: value.expectile must lie in (0, 1), got 1.5."]
    # hydra used to create run_dir, .hydra/ and a job log before the config was validated
    assert [p.name for p in tmp_path.iterdir()] == ["launch"]
    assert list(launch.iterdir()) == []


def test_cli_run_writes_only_into_run_dir(tmp_path):
    launch = tmp_path / "launch"
    launch.mkdir()
    proc = run_cli(tmp_path, f"run_dir={tmp_path / 'run'}", cwd=launch)
    assert proc.returncode == 0, proc.stderr
    assert list(launch.iterdir()) == []
    written = {p.name for p in (tmp_path / "run").iterdir()}
    assert {"config.yaml", "results.json", "tsidm.pt", "policy.pt", "eval_scores.png", "monitor.pt",
            "monitor_scores.png"} <= written
    assert not written & {".hydra", "tels_offline.log"}
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    # two stage-1 steps still leave a final loss to pick beta by (it was nan under 10 steps)
    (result,) = results["beta_results"]
    assert math.isfinite(result["final_loss"]) and math.isfinite(result["final_sum"])
    # the final evaluation's monitor record: a fraction, with the per-step scores left to the plot
    assert 0 <= results["monitor"]["ood_fraction"] <= 1 and results["monitor"]["quantile"] == 0.99
    assert 0 <= results["monitor"]["alarm_fraction"] <= 1 and results["monitor"]["window_quantile"] == 0.999
    assert not {"scores", "windows"} & set(results["evaluations"][-1]["monitor"])


def test_cli_unwritable_output_folder(tmp_path):
    # A folder under a regular file cannot be created, even by root (chmod would not stop root).
    (tmp_path / "a_file").write_text("")
    proc = run_cli(tmp_path, f"run_dir={tmp_path / 'a_file' / 'run'}")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"error: run_dir {tmp_path / 'a_file' / 'run'} is not writable: Not a directory."
    ]


def test_cli_config_key_that_does_not_exist(tmp_path):
    proc = run_cli(tmp_path, f"run_dir={tmp_path / 'run'}", "value.expectle=0.5")
    # hydra rejects the override before the recipe runs: its message, no traceback, nothing written.
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    assert "Could not override 'value.expectle'." in proc.stderr
    assert "Key 'expectle' is not in struct" in proc.stderr
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------- checkpoint files
def test_load_checkpoint_uses_weights_only(tmp_path):
    marker = tmp_path / "code_ran"
    torch.save({"format": "x/v1", "payload": _Payload(marker)}, tmp_path / "hostile.pt")
    with pytest.raises(CheckpointError, match="not a torchrl_tels checkpoint"):
        load_checkpoint(tmp_path / "hostile.pt", "x/v1")
    assert not marker.exists()
    with open(tmp_path / "plain.pkl", "wb") as f:  # a plain pickle, not even a torch file
        pickle.dump(_Payload(marker), f, protocol=2)
    with pytest.raises(CheckpointError, match="truncated, corrupted, or not a torchrl_tels checkpoint"):
        load_checkpoint(tmp_path / "plain.pkl", "x/v1")
    assert not marker.exists()
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "absent.pt", "x/v1")


def test_failed_write_keeps_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "state.pt"
    atomic_save({"format": "x/v1", "version": 1}, path)

    def save_half_then_fail(obj, f):
        f.write(b"PK\x03\x04 half a zip")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", save_half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        atomic_save({"format": "x/v1", "version": 2}, path)
    monkeypatch.undo()
    assert load_checkpoint(path, "x/v1")["version"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"]  # the temporary file is gone too


_WRITER = """
import sys, torch
from torchrl_tels.checkpoint import atomic_save
big = torch.zeros(8_000_000)
for version in range(1, 10_000):
    atomic_save({"format": "x/v1", "version": version, "weights": big.fill_(version)}, sys.argv[1])
    print(version, flush=True)
"""


def test_sigkill_during_write_leaves_previous_good_file(tmp_path):
    """SIGKILL a process that rewrites a 32 MB checkpoint in a loop: the file on disk is always whole.

    Most of each loop is spent writing, so the kill lands mid-write; a leftover
    temporary file shows that it did (retried a few times until it does).
    """
    path = tmp_path / "state.pt"
    for attempt, delay in enumerate((0.05, 0.13, 0.21, 0.34, 0.55)):
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "1"  # one complete file exists
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        state = load_checkpoint(path, "x/v1")
        assert torch.all(state["weights"] == state["version"])
        if list(tmp_path.glob(".state.pt.*.tmp")):
            return  # killed mid-write, and the previous file is intact
    pytest.fail("no kill landed during a write")


def test_checkpoint_refuses_non_finite_weights(tmp_path):
    path = tmp_path / "state.pt"
    save_training_state(path, {"stage": "policy", "step": 25, "value_loss": {"w": torch.ones(3)}})
    good = path.read_bytes()
    bad = {"stage": "policy", "step": 50, "value_loss": {"w": torch.tensor([1.0, float("nan"), 2.0])}}
    with pytest.raises(NonFiniteLossError, match=r"checkpoint state.pt: value_loss.w holds NaN or inf"):
        save_training_state(path, bad)
    assert path.read_bytes() == good
    assert load_training_state(path)["step"] == 25


def test_user_errors_are_tels_errors():
    """The CLI shows a TelsError as one line; anything else (a bug, torch) keeps its traceback."""
    assert is_user_error(ConfigError("x")) and is_user_error(NonFiniteLossError("x"))
    with pytest.raises(ConfigError) as info:
        validate_config(compose_cfg("run_dir=x", "value.gamma=2"))
    assert is_user_error(info.value)
    with pytest.raises(ValueError) as info:  # an unknown task: a TelsError that is also a ValueError
        from torchrl_tels.envs import get_task

        get_task("no-such-task")
    assert isinstance(info.value, TelsError)
    with pytest.raises(RuntimeError) as info:
        torch.zeros(2).view(3)
    assert not is_user_error(info.value)
    with pytest.raises(ValueError) as info:  # a ValueError from inside torch is a bug: shown in full
        torch.nn.functional.cross_entropy(torch.zeros(2, 3), torch.zeros(3, dtype=torch.long))
    assert not is_user_error(info.value)


def test_actions_outside_the_env_bounds_are_refused(recipe, capsys, tmp_path):
    arrays = hopper_arrays()
    arrays["actions"] = arrays["actions"] * 5
    outside = int((np.abs(arrays["actions"]) > 1).any(-1).sum())
    path = write_npz(tmp_path / "hopper_x5.npz", arrays)
    message = expect_error(recipe, capsys, tmp_path / "run", f"dataset.name={path}", "dataset.task=hopper-medium-v2")
    assert f"{outside} of {len(arrays['actions'])} actions lie outside the action bounds of Hopper-v4" in message
    assert "[-1, 1]" in message


# ------------------------------------------------------------------- wandb
@pytest.fixture
def offline_wandb_env(monkeypatch, tmp_path):
    """No stored login, and any server address points to a closed local port: nothing leaves this machine."""
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "home" / ".config" / "wandb"))
    monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")
    monkeypatch.delenv("WANDB_MODE", raising=False)


def _csv_rows(log_dir: Path, name: str) -> list[str]:
    return (log_dir / "csv" / "scalars" / f"{name}.csv").read_text().splitlines()


def _log_three(logger: RunLogger) -> None:
    for step in (1, 2, 3):
        logger.log_scalars({"train/loss": 0.5 * step}, step)
    logger.close()


def _wandb_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if "wandb is off for this run" in str(w.message)]


def test_wandb_without_login_falls_back_to_csv(tmp_path, offline_wandb_env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        logger = RunLogger(tmp_path / "run", "tels", wandb_mode="online")
        assert logger.wandb is None
        _log_three(logger)
    assert len(_wandb_warnings(caught)) == 1
    assert _csv_rows(tmp_path / "run", "train/loss") == ["1,0.5", "2,1.0", "3,1.5"]


def test_wandb_without_network_falls_back_to_csv(tmp_path, offline_wandb_env, monkeypatch):
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)  # a login, but the server cannot be reached
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        logger = RunLogger(tmp_path / "run", "tels", wandb_mode="online", wandb_init_timeout=2)
        assert logger.wandb is None
        _log_three(logger)
    assert len(_wandb_warnings(caught)) == 1
    assert _csv_rows(tmp_path / "run", "train/loss") == ["1,0.5", "2,1.0", "3,1.5"]


def test_wandb_error_mid_run_falls_back_to_csv(tmp_path, monkeypatch):
    import torchrl.record.loggers as loggers

    class FlakyWandb:
        """Starts fine, then every call fails, as a wandb whose service died would."""

        def __init__(self, **kwargs):
            self.experiment = type("Run", (), {"id": "abc123"})()
            self.calls = 0

        def log_scalar(self, name, value, step=None):
            self.calls += 1
            if self.calls > 1:
                raise ConnectionError("wandb service went away")

    monkeypatch.setattr(loggers, "WandbLogger", FlakyWandb)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        logger = RunLogger(tmp_path / "run", "tels", wandb_mode="offline")
        assert logger.wandb_id == "abc123"
        _log_three(logger)
        assert logger.wandb is None
    messages = _wandb_warnings(caught)
    assert len(messages) == 1 and "ConnectionError: wandb service went away" in messages[0]
    assert _csv_rows(tmp_path / "run", "train/loss") == ["1,0.5", "2,1.0", "3,1.5"]


def test_write_text_replaces_whole_file_and_leaves_no_temp(tmp_path, monkeypatch):
    target = tmp_path / "TABLE.md"
    write_text(target, "old")
    # A failure while writing the new text must leave the old file as it was.
    real_write = Path.write_text

    def failing_write(self, text, *args, **kwargs):
        real_write(self, text[:2], *args, **kwargs)
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_text", failing_write)
    with pytest.raises(OSError, match="disk full"):
        write_text(target, "new table")
    monkeypatch.undo()
    assert target.read_text() == "old"
    assert not list(tmp_path.glob("*.tmp")), "the failed write left its temporary file"
    write_text(target, "new table")
    write_json(tmp_path / "r.json", {"b": 1, "a": 2})
    assert target.read_text() == "new table"
    assert (tmp_path / "r.json").read_text() == '{\n  "a": 2,\n  "b": 1\n}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["TABLE.md", "r.json"]


def test_config_groups_compose_domain_and_budget():
    """The base is the paper; ``domain=mujoco`` departs where README's deviation table says,
    ``domain=maze`` takes Table 11's AntMaze values, ``domain=adroit`` and ``domain=adroit_paper`` take Tables
    10-11's values for other tasks and select β as App. B.5 does, and the budget group only sets lengths."""
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        paper = compose("config", overrides=["domain=paper", "budget=paper"])
        mujoco, maze = compose("config"), compose("config", overrides=["domain=maze", "budget=paper"])
        adroit = compose("config", overrides=["domain=adroit"])
        adroit_paper = compose("config", overrides=["domain=adroit_paper", "budget=paper"])
        smoke = compose("config", overrides=["budget=smoke"])
    assert (adroit.guide.alpha, adroit.value.expectile, adroit.tsidm.weight_decay) == (0.01, 0.7, 1e-5)
    assert adroit.guide.alpha != mujoco.guide.alpha and adroit.tsidm.beta == "auto"
    assert adroit.guide.reencode_proposal is False and adroit.guide.mode == "deterministic"
    assert mujoco.guide.mode == "deterministic" and mujoco.guide.reencode_proposal is True
    assert maze.guide.mode == "stochastic" and maze.guide.reencode_proposal is False
    # App. B.5: "other domains" select beta by the TS-IDM loss; the paper's reading departs nowhere else
    assert adroit_paper.tsidm.beta == "auto" and adroit_paper.tsidm.beta_selection == paper.tsidm.beta_selection
    assert adroit_paper.guide == paper.guide and adroit_paper.tsidm.weight_decay == 1e-5
    # the default on Adroit keeps no MuJoCo departure: the paper's reading but for the episode budget group
    assert adroit.guide == adroit_paper.guide and adroit.tsidm.beta_selection == adroit_paper.tsidm.beta_selection
    assert paper.tsidm.beta == 1.0 and maze.tsidm.beta == 1.0
    assert paper.guide.alpha == 0.01 and maze.guide.alpha == 10.0
    assert paper.tsidm.latent_scale == "free" and paper.guide.tsym_relative is False
    assert (mujoco.tsidm.steps, mujoco.policy.steps, mujoco.eval.interval) == (3000, 5000, 500)
    assert (paper.tsidm.steps, paper.tsidm.epochs, paper.policy.steps) == (None, 1000, 100_000)
    assert (maze.tsidm.steps, maze.tsidm.epochs, maze.policy.steps) == (None, 1000, 100_000)
    # The smoke run exercises the default domain's choices, only smaller and shorter.
    for section in ("guide", "tsidm", "value"):
        for key in ("reencode_proposal", "alpha", "beta", "latent_scale", "tsym_relative", "expectile"):
            if key in mujoco[section]:
                assert smoke[section][key] == mujoco[section][key], (section, key)
    assert mujoco.eval.last_n == 10 and mujoco.eval.episodes == 10
    assert mujoco.value.target_update_rate == 0.05
