"""recipes/export_policy.py: programs that load with torch alone and act as the library does; refusals write nothing."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchrl.envs import GymEnv

from torchrl_tels.envs import DeploymentMonitor
from torchrl_tels.envs.monitor import running_mean
from torchrl_tels.export import export_run
from torchrl_tels.modules import load_tels_actor, make_guide_policy, save_guide_policy, TSIDM

REPO_ROOT = Path(__file__).resolve().parents[1]
OBS_DIM, ACTION_DIM, LATENT_DIM = 11, 3, 8  # Hopper-v4
CELLS = (32, 32)
N = 1000
WINDOW = 3


def tiny_tsidm(latent_dim: int = LATENT_DIM, observation_dim: int = OBS_DIM, standardized: bool = False) -> TSIDM:
    tsidm = TSIDM(observation_dim, ACTION_DIM, latent_state_dim=latent_dim, encoder_cells=CELLS,
                  decoder_cells=CELLS, inverse_cells=CELLS, action_decoder_cells=CELLS, dynamics_cells=CELLS,
                  latent_standardization=standardized)
    tsidm.set_state_normalization(torch.linspace(-1.0, 1.0, observation_dim),
                                  torch.linspace(0.5, 2.0, observation_dim))
    if standardized:
        tsidm.fit_latent_standardization(torch.randn(200, observation_dim))
    with torch.no_grad():  # actions spread past the bounds, so the clipping is exercised
        tsidm.action_decoder[-1].weight.mul_(30.0)
    return tsidm.eval()


def make_run(run_dir: Path, *, mode: str = "deterministic", standardized: bool = False, reencode: bool = False,
             monitor: bool = False) -> Path:
    """A finished run folder made the fast way: the files the recipe writes, without training."""
    run_dir.mkdir(parents=True)
    tsidm = tiny_tsidm(standardized=standardized)
    tsidm.save(run_dir / "tsidm.pt")
    guide = make_guide_policy(LATENT_DIM, mode, CELLS)
    save_guide_policy(run_dir / "policy.pt", guide, latent_dim=LATENT_DIM, mode=mode, num_cells=CELLS,
                      actor_options={"reencode_proposal": reencode})
    if monitor:
        data = transitions(600)
        m = DeploymentMonitor.fit(data[:400], data[400:], tsidm=tsidm, members=2, num_cells=CELLS, steps=20,
                                  quantile=0.9, window=WINDOW, window_quantile=0.9)
        m.save(run_dir / "monitor.pt", metadata={"dataset": "hopper-medium-v2-10k"})
    (run_dir / "results.json").write_text(json.dumps({"env": "Hopper-v4", "dataset": "hopper-medium-v2-10k",
                                                      "final_normalized_score_mean": 0.0}))
    (run_dir / "config.yaml").write_text("monitor: {folds: 2, members: 2, num_cells: [16, 16], steps: 20, "
                                         "window: 5, window_quantile: 0.99}\n")
    return run_dir


def transitions(n: int, seed: int = 0):
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(seed)
    observation = 2 * torch.randn(n, OBS_DIM, generator=g)
    return TensorDict({"observation": observation, "action": torch.rand(n, ACTION_DIM, generator=g) * 2 - 1,
                       ("next", "observation"): observation + 0.1 * torch.randn(n, OBS_DIM, generator=g),
                       "episode": torch.arange(n) // 50}, [n])


def run_fresh_torch(code: str, cwd: Path) -> subprocess.CompletedProcess:
    """``code`` in a new interpreter that imports torch only (and checks it stayed that way)."""
    check = ("import sys\nleaked = sorted({m.split('.')[0] for m in sys.modules} & "
             "{'tensordict', 'torchrl', 'torchrl_tels'})\nassert not leaked, leaked\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["OMP_NUM_THREADS"] = "1"
    result = subprocess.run([sys.executable, "-c", "import torch\n" + code + check], cwd=cwd, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def library_actions(run_dir: Path, observation: torch.Tensor) -> torch.Tensor:
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    actor = load_tels_actor(run_dir / "policy.pt", run_dir / "tsidm.pt", GymEnv("Hopper-v4").action_spec)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return actor(TensorDict({"observation": observation}, [len(observation)]))["action"]


# ------------------------------------------------------------------ the programs
@pytest.mark.parametrize("options", [
    {},
    {"mode": "stochastic", "standardized": True, "reencode": True},
])
def test_exported_programs_load_with_torch_alone_and_compute_what_the_library_does(tmp_path, options):
    run_dir = make_run(tmp_path / "run", monitor=True, **options)
    written = export_run(run_dir, log=lambda message: None)
    assert sorted(written) == ["export.json", "monitor.pt2", "policy.pt2"]
    data = transitions(N, seed=3)
    steps = [data[i * 250:(i + 1) * 250] for i in range(4)]  # four steps of a batch of 250 streams
    torch.save({"observation": data["observation"], "steps": [(t["observation"], t["action"], t["next", "observation"])
                                                              for t in steps]}, tmp_path / "transitions.pt")
    run_fresh_torch("t = torch.load('transitions.pt')\n"
                    "p = torch.export.load('run/export/policy.pt2').module()\n"
                    "m = torch.export.load('run/export/monitor.pt2').module()\n"
                    f"recent, count = torch.zeros(250, {WINDOW}), torch.zeros(250, 1, dtype=torch.long)\n"
                    "outs = []\n"
                    "for o, a, o2 in t['steps']:\n"
                    "    *out, recent, count = m(o, a, o2, recent, count)\n"
                    "    outs.append(out)\n"
                    "torch.save({'actions': p(t['observation']), 'monitor': outs}, 'out.pt')\n", tmp_path)
    out = torch.load(tmp_path / "out.pt")

    expected = library_actions(run_dir, data["observation"])
    assert out["actions"].shape == (N, ACTION_DIM)
    torch.testing.assert_close(out["actions"], expected, rtol=0, atol=1e-5)
    # the clipping is part of the program: some actions sit on the bounds, none beyond
    assert (expected.abs() == 1).float().mean() > 0.05 and out["actions"].abs().max() <= 1

    monitor = DeploymentMonitor.load(run_dir / "monitor.pt")
    scores = torch.stack([monitor(t.clone())["next", "ood_score"].squeeze(-1) for t in steps], -1)  # (250, 4)
    windows = running_mean(scores, WINDOW).float()
    for k, (score, ood, window, alarm) in enumerate(out["monitor"]):
        torch.testing.assert_close(score, scores[:, k], rtol=1e-5, atol=1e-5)
        assert torch.equal(ood, score > monitor.threshold)
        torch.testing.assert_close(window, windows[:, k], rtol=1e-5, atol=1e-5)
        assert torch.equal(alarm, window > monitor.window_threshold)
    flags = torch.stack([o[1] for o in out["monitor"]])
    assert 0 < flags.float().mean() < 1
    manifest = json.loads((run_dir / "export" / "export.json").read_text())
    assert manifest["observation_dim"] == OBS_DIM and manifest["action_high"] == [1.0, 1.0, 1.0]


def test_calibrate_option_exports_a_monitor_fitted_to_the_dataset_with_the_runs_settings(tmp_path):
    run_dir = make_run(tmp_path / "run")
    written = export_run(run_dir, tmp_path / "out", calibrate="hopper-medium-v2-10k", quantile=0.95,
                         log=lambda message: None)
    assert {"monitor.pt2", "monitor.pt"} <= set(written)
    monitor = DeploymentMonitor.load(written["monitor.pt"])
    # the run's config.yaml: 2 folds, 2 members of 16 units, a window of 5 steps
    assert monitor.metadata["calibration"] == "cross_fit_2" and monitor.metadata["dataset"] == "hopper-medium-v2-10k"
    assert monitor.dynamics.members == 2 and monitor.dynamics.num_cells == (16, 16) and monitor.window == 5
    manifest = json.loads(written["export.json"].read_text())["monitor"]
    assert manifest["quantile"] == 0.95 and manifest["window_quantile"] == 0.99
    assert manifest["threshold"] == float(monitor.threshold)


def test_policy_only_without_a_monitor_says_so(tmp_path):
    run_dir = make_run(tmp_path / "run")
    said = []
    written = export_run(run_dir, log=said.append)
    assert sorted(written) == ["export.json", "policy.pt2"] and "exporting the policy only" in said[0]


def test_onnx_files_match_the_library(tmp_path):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    ort = pytest.importorskip("onnxruntime")
    run_dir = make_run(tmp_path / "run", monitor=True, standardized=True)
    written = export_run(run_dir, onnx=True, log=lambda message: None)
    assert {"policy.onnx", "monitor.onnx"} <= set(written)
    observation = transitions(N)["observation"]
    session = ort.InferenceSession(str(written["policy.onnx"]), providers=["CPUExecutionProvider"])
    (action,) = session.run(None, {session.get_inputs()[0].name: observation.numpy()})
    torch.testing.assert_close(torch.from_numpy(action), library_actions(run_dir, observation), rtol=0, atol=1e-5)


def test_onnx_without_its_packages_is_skipped_with_a_message(tmp_path, monkeypatch):
    import torchrl_tels.export as export_module

    monkeypatch.setattr(export_module, "onnx_missing", lambda: "onnx not installed")
    said = []
    written = export_run(make_run(tmp_path / "run"), onnx=True, log=said.append)
    assert "policy.onnx" not in written and any("onnx not installed; skipping" in s for s in said)


# ------------------------------------------------------------------ refusals
def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def expect_refusal(run_dir: Path, capsys, *args: str) -> str:
    """The CLI's main: exit code 2, one ``error:`` line, the run folder unchanged and no export folder."""
    spec = importlib.util.spec_from_file_location("export_policy", REPO_ROOT / "recipes" / "export_policy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    before = _tree(run_dir) if run_dir.exists() else {}
    capsys.readouterr()
    assert module.main([str(run_dir), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    if run_dir.exists():
        assert _tree(run_dir) == before
        assert sorted(p.name for p in run_dir.iterdir()) == sorted(before)  # no export/, no hidden staging
    return err[0]


def test_unfinished_run_is_refused(tmp_path, capsys):
    run_dir = make_run(tmp_path / "run")
    (run_dir / "results.json").unlink()
    assert "no results.json: the run has not finished" in expect_refusal(run_dir, capsys)


def test_missing_tsidm_is_refused(tmp_path, capsys):
    run_dir = make_run(tmp_path / "run")
    (run_dir / "tsidm.pt").unlink()
    assert "tsidm.pt does not exist" in expect_refusal(run_dir, capsys)


def test_foreign_tsidm_is_refused(tmp_path, capsys):
    run_dir = make_run(tmp_path / "run")
    tiny_tsidm(latent_dim=5).save(run_dir / "tsidm.pt")  # another run's: its latent differs from policy.pt's
    assert "8-dim latent space, but the TS-IDM's latent state has 5 dims" in expect_refusal(run_dir, capsys)
    tiny_tsidm(observation_dim=17).save(run_dir / "tsidm.pt")  # another env's
    assert "observation_dim=17, but this environment/dataset has observation_dim=11" in expect_refusal(
        run_dir, capsys)


def test_monitor_of_another_task_is_refused(tmp_path, capsys):
    run_dir = make_run(tmp_path / "run", monitor=True)
    other = DeploymentMonitor.load(run_dir / "monitor.pt")
    other.save(run_dir / "monitor.pt", metadata={"dataset": "walker2d-medium-v2-10k"})
    assert "fitted to 'walker2d-medium-v2-10k', but the run trained on 'hopper-medium-v2-10k'" in expect_refusal(
        run_dir, capsys)


def test_bad_calibration_data_and_out_folder_are_refused(tmp_path, capsys):
    run_dir = make_run(tmp_path / "run")
    message = expect_refusal(run_dir, capsys, "--calibrate", str(walker_npz(tmp_path)))
    assert "observations have size 17, but the run's environment's have size 11" in message
    assert "--quantile must lie in (0, 1)" in expect_refusal(run_dir, capsys, "--calibrate", "hopper-medium-v2-10k",
                                                          "--quantile", "1.5")
    assert "does not exist" in expect_refusal(run_dir, capsys, "--out", str(tmp_path / "no" / "such"))
    assert not (tmp_path / "no").exists()


def walker_npz(tmp_path: Path) -> Path:
    """A small D4RL-style file with Walker2d's sizes (17/6)."""
    import numpy as np

    rng = np.random.default_rng(0)
    arrays = {"observations": rng.normal(size=(50, 17)), "actions": rng.uniform(-1, 1, (50, 6)),
              "next_observations": rng.normal(size=(50, 17)), "rewards": rng.normal(size=50),
              "terminals": np.zeros(50, bool), "timeouts": np.zeros(50, bool)}
    np.savez(tmp_path / "walker.npz", **arrays)
    return tmp_path / "walker.npz"


def test_a_failure_while_writing_leaves_no_folder_and_keeps_an_old_export(tmp_path, monkeypatch):
    run_dir = make_run(tmp_path / "run", monitor=True)
    real_save = torch.export.save

    def save_then_fail(program, path, *args, **kwargs):
        real_save(program, path, *args, **kwargs)
        if Path(path).name == "monitor.pt2":
            raise OSError("disk full")

    monkeypatch.setattr(torch.export, "save", save_then_fail)
    with pytest.raises(OSError, match="disk full"):
        export_run(run_dir, log=lambda message: None)
    assert sorted(p.name for p in run_dir.iterdir()) == ["config.yaml", "monitor.pt", "policy.pt", "results.json",
                                                         "tsidm.pt"]
    monkeypatch.setattr(torch.export, "save", real_save)
    export_run(run_dir, log=lambda message: None)
    old = _tree(run_dir / "export")
    monkeypatch.setattr(torch.export, "save", save_then_fail)
    with pytest.raises(OSError, match="disk full"):
        export_run(run_dir, log=lambda message: None)
    assert _tree(run_dir / "export") == old  # the previous export is untouched
    assert not [p for p in run_dir.iterdir() if p.name.startswith(".")]


def test_cli_exit_code_and_error_line(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "export_policy.py"), str(run_dir)],
                            env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: {run_dir} has no results.json: the run has not finished (or it is not a run folder); "
        "finish it with resume=true, then export."]
    assert list(run_dir.iterdir()) == []
