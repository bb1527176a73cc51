"""``run_grid --tsidm-from``: a TELS run starts stage 2 from an earlier grid's TS-IDM only when that stage 1
had the same settings (``torchrl_tels.config.stage1_differences``)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from benchmarks import run_grid
from benchmarks.harness import recipe_config, with_pinned_precision
from torchrl_tels.config import stage1_differences, training_config
from torchrl_tels.modules import TSIDM

TASK = "hopper-medium-v2-10k"


def _config(*overrides: str) -> dict:
    return training_config(recipe_config(["precision=fp32", *overrides]))


def test_stage1_differences_name_stage1_settings_only():
    base = _config()
    assert stage1_differences(base, _config("guide.alpha=0.01", "policy.steps=7", "eval.episodes=3",
                                            "dataset.reward_scale=2.0", "dataset.reward_bias=-1.0")) == []
    assert stage1_differences(base, _config("tsidm.checkpoint=/somewhere/tsidm.pt")) == []
    assert stage1_differences(base, _config("tsidm.beta=1.0")) == ["tsidm.beta: 0.01 -> 1.0"]
    steps = base["tsidm"]["steps"]
    assert stage1_differences(base, _config("seed=3", "tsidm.steps=9")) == ["seed: 0 -> 3", f"tsidm.steps: {steps} -> 9"]


STAGE1_LOSS = [{"beta": 0.01, "final_loss": 1.25, "final_sum": 2.5}]


def _tsidm_file(path: Path, dataset: str = TASK, beta: float = 0.01) -> None:
    """A small TS-IDM file with the metadata a finished stage 1 writes."""
    TSIDM(observation_dim=3, action_dim=2, encoder_cells=[8], decoder_cells=[8], inverse_cells=[8],
          action_decoder_cells=[8], dynamics_cells=[8]).save(
        path, metadata={"beta": beta, "dataset": dataset, "beta_results": STAGE1_LOSS})


def _fake_recipe(calls: list):
    """Writes what the recipe leaves in its run folder that the grid reads: config.yaml, state.pt, tsidm.pt,
    results.json."""

    def run_recipe(overrides, threads=None):
        calls.append(list(overrides))
        run_dir = Path(next(o.split("=", 1)[1] for o in overrides if o.startswith("run_dir=")))
        run_dir.mkdir(parents=True, exist_ok=True)
        cfg = recipe_config(with_pinned_precision(overrides))
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
        (run_dir / "state.pt").write_bytes(b"a run's state")
        beta = 1.0 if cfg.tsidm.beta == "auto" else float(cfg.tsidm.beta)  # the candidate "auto" selected
        _tsidm_file(run_dir / "tsidm.pt", dataset=cfg.dataset.name, beta=beta)
        (run_dir / "results.json").write_text(json.dumps({"final_normalized_score_mean": 1.0, "budget": {}}))
        return ["recipe", *overrides]

    return run_recipe


def _grid(tmp_path: Path, work: str, *extra: str):
    return run_grid.parse_args(["--method", "tels", "--task", TASK, "--seed", "1", "--steps", "10",
                                "--tsidm-steps", "5", "--eval-interval", "5", "--results-dir", str(tmp_path / work),
                                "--work-dir", str(tmp_path / work), *extra])


def _checkpoint_overrides(call: list[str]) -> list[str]:
    return [o for o in call if o.startswith("tsidm.checkpoint=")]


def test_tsidm_from_reuses_a_matching_stage1_and_trains_its_own_otherwise(tmp_path, monkeypatch, capsys):
    calls: list = []
    monkeypatch.setattr(run_grid, "run_recipe", _fake_recipe(calls))
    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "first"))
    source = tmp_path / "first" / "tels" / TASK / "seed1"
    assert _checkpoint_overrides(calls[-1]) == []

    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "second", "--tsidm-from", str(tmp_path / "first")))
    assert _checkpoint_overrides(calls[-1]) == [f"tsidm.checkpoint={source / 'tsidm.pt'}"]
    record = json.loads(run_grid.result_path(tmp_path / "second", "tels", TASK, 1).read_text())
    assert f"tsidm.checkpoint={source / 'tsidm.pt'}" in record["recipe_overrides"]
    assert record["tsidm_reused"] == {"from": str(source / "tsidm.pt"), "beta_results": STAGE1_LOSS}
    assert "--tsidm-from" in " ".join(run_grid.one_command(_grid(tmp_path, "x", "--tsidm-from", str(source)),
                                                           "tels", TASK, 1))

    # resumed (or recorded again) without the flag, the run keeps the TS-IDM it started from
    run_grid.result_path(tmp_path / "second", "tels", TASK, 1).unlink()
    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "second"))
    assert _checkpoint_overrides(calls[-1]) == [f"tsidm.checkpoint={source / 'tsidm.pt'}"]

    saved = yaml.safe_load((source / "config.yaml").read_text())
    saved["tsidm"]["beta"] = 1.0
    (source / "config.yaml").write_text(yaml.safe_dump(saved))
    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "third", "--tsidm-from", str(tmp_path / "first")))
    assert _checkpoint_overrides(calls[-1]) == []
    assert "tsidm.beta: 1.0 -> 0.01" in capsys.readouterr().out

    saved["tsidm"]["beta"] = 0.01
    (source / "config.yaml").write_text(yaml.safe_dump(saved))
    _tsidm_file(source / "tsidm.pt", dataset="walker2d-medium-v2-10k")  # config.yaml no longer describes it
    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "fourth", "--tsidm-from", str(tmp_path / "first")))
    assert _checkpoint_overrides(calls[-1]) == []
    assert "is not the TS-IDM the stage 1" in capsys.readouterr().out

    (source / "tsidm.pt").unlink()
    run_grid.run_one("tels", TASK, 1, _grid(tmp_path, "fifth", "--tsidm-from", str(tmp_path / "first")))
    assert _checkpoint_overrides(calls[-1]) == []
    assert "no finished stage 1" in capsys.readouterr().out

    with pytest.raises(SystemExit):
        _grid(tmp_path, "first", "--tsidm-from", str(tmp_path / "first"))


def test_tsidm_from_method_reuses_another_arms_stage1_only_with_the_same_settings(tmp_path, monkeypatch, capsys):
    """On Adroit the default and the paper's reading share their stage-1 settings, on MuJoCo they do not."""
    calls: list = []
    monkeypatch.setattr(run_grid, "run_recipe", _fake_recipe(calls))

    def grid(method: str, task: str, work: str, *extra: str):
        return run_grid.parse_args(["--method", method, "--task", task, "--seed", "1", "--steps", "10",
                                    "--tsidm-steps", "5", "--eval-interval", "5", "--results-dir",
                                    str(tmp_path / work), "--work-dir", str(tmp_path / work), *extra])

    for task in ("door-human-v1", TASK):
        run_grid.run_one("tels_paper", task, 1, grid("tels_paper", task, "paper"))
    reuse = ("--tsidm-from", str(tmp_path / "paper"), "--tsidm-from-method", "tels_paper")
    run_grid.run_one("tels", "door-human-v1", 1, grid("tels", "door-human-v1", "default", *reuse))
    source = tmp_path / "paper" / "tels_paper" / "door-human-v1" / "seed1" / "tsidm.pt"
    assert _checkpoint_overrides(calls[-1]) == [f"tsidm.checkpoint={source}"]
    record = json.loads(run_grid.result_path(tmp_path / "default", "tels", "door-human-v1", 1).read_text())
    assert record["tsidm_reused"]["from"] == str(source)
    assert "--tsidm-from-method=tels_paper" in run_grid.one_command(grid("tels", TASK, "x", *reuse), "tels", TASK, 1)
    with pytest.raises(SystemExit):
        grid("tels", TASK, "y", "--tsidm-from-method", "tels_paper")

    run_grid.run_one("tels", TASK, 1, grid("tels", TASK, "default", *reuse))
    assert _checkpoint_overrides(calls[-1]) == []
    assert "tsidm.beta: 1.0 -> 0.01" in capsys.readouterr().out


def test_the_report_pairs_two_runs_only_on_one_tsidm():
    from study.domains import same_tsidm

    alpha1 = {"run_dir": "../main/runs/exp/tels/pen-expert-v1-10k/seed0", "beta_results": [{"final_loss": 2.03}]}
    assert same_tsidm({"tsidm_reused": {"beta_results": [{"final_loss": 2.03}]}, "beta_results": []}, alpha1)
    assert not same_tsidm({"tsidm_reused": {"beta_results": [{"final_loss": 2.5}]}, "beta_results": []}, alpha1)
    assert same_tsidm({"recipe_overrides": ["seed=0"], "beta_results": [{"final_loss": 2.03}]}, alpha1)
    assert not same_tsidm({"recipe_overrides": ["seed=0"], "beta_results": [{"final_loss": 2.04}]}, alpha1)
    # a run that recorded no losses: its checkpoint's run folder decides
    study_arm = {"overrides": ["guide.alpha=0.01", "tsidm.checkpoint=../elsewhere/runs/exp/tels/pen-expert-v1-10k/seed0/tsidm.pt"]}
    assert same_tsidm(study_arm, alpha1)
    assert not same_tsidm(study_arm, {**alpha1, "beta_results": [], "run_dir": "runs/grid/tels/pen-expert-v1-10k/seed0"})
    assert not same_tsidm({"recipe_overrides": [], "beta_results": []}, {**alpha1, "beta_results": []})
    # a grid run that itself reused a TS-IDM acted with the one in the folder it reused it from
    reusing_grid_run = {"run_dir": "runs/grid/tels/pen-expert-v1-10k/seed0", "beta_results": [],
                        "recipe_overrides": ["tsidm.checkpoint=../main/runs/exp/tels/pen-expert-v1-10k/seed0/tsidm.pt"]}
    assert same_tsidm(study_arm, reusing_grid_run)
    assert not same_tsidm(study_arm, {**reusing_grid_run, "recipe_overrides": [
        "tsidm.checkpoint=../main/runs/exp/tels/pen-expert-v1-10k/seed1/tsidm.pt"]})
    # a beta=auto run acted on the candidate it selected: it pairs with a run of that beta's TS-IDM, not another's
    auto = {"beta": 0.01, "beta_results": [{"beta": 0.01, "final_loss": 2.03}, {"beta": 0.1, "final_loss": 2.4},
                                           {"beta": 1.0, "final_loss": 3.1}]}
    assert same_tsidm(auto, {**alpha1, "beta": 0.01})
    assert not same_tsidm({**auto, "beta": 1.0}, {**alpha1, "beta": 0.01})


def test_the_alpha0_arm_sets_alpha_to_zero_and_starts_from_the_default_runs_stage1(tmp_path, monkeypatch):
    """α = 0 changes stage 2 only, so the arm's stage 1 is the default's: it may start from that run's TS-IDM."""
    calls: list = []
    monkeypatch.setattr(run_grid, "run_recipe", _fake_recipe(calls))
    task = "antmaze-umaze-v0-10k"

    def grid(method: str, *extra: str):
        return run_grid.parse_args(["--method", method, "--task", task, "--seed", "2", "--steps", "10",
                                    "--tsidm-steps", "5", "--eval-interval", "5", "--results-dir",
                                    str(tmp_path / "results"), "--work-dir", str(tmp_path / "work"), *extra])

    run_grid.run_one("tels", task, 2, grid("tels"))
    assert not any(o.startswith("guide.alpha=") for o in calls[-1])
    run_grid.run_one("tels_alpha0", task, 2, grid("tels_alpha0", "--tsidm-from", str(tmp_path / "work"),
                                                  "--tsidm-from-method", "tels"))
    assert "guide.alpha=0" in calls[-1] and "domain=maze" in calls[-1]
    source = tmp_path / "work" / "tels" / task / "seed2" / "tsidm.pt"
    assert _checkpoint_overrides(calls[-1]) == [f"tsidm.checkpoint={source}"]
    assert run_grid.result_path(tmp_path / "results", "tels_alpha0", task, 2).is_file()
