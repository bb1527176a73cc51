"""Several seeds in one process (``seeds=[...]``): stacked parameters, one vmapped update.

A stacked update must be each seed's own update: the same losses and gradients
as the seed's module alone, and, end to end, the same networks as the seed's
single-seed run (within float tolerance: vmap's batched matmuls round
differently). A killed multi-seed run must resume bitwise.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from tests.recipe_process import DRIVER, RECIPE, recipe_env, REPO_ROOT
from torchrl_tels.modules import make_latent_value, TSIDM
from torchrl_tels.objectives import LatentExpectileLoss, TSIDMLoss
from torchrl_tels.seeds import SeedRNG, StackedLoss
from torchrl_tels.training import load_training_state, sum_losses

OBS, ACT, BATCH = 5, 2, 16


def _tsidm_loss(seed: int) -> TSIDMLoss:
    torch.manual_seed(seed)
    tsidm = TSIDM(OBS, ACT, encoder_cells=[32], decoder_cells=[32], inverse_cells=[32], action_decoder_cells=[32],
                  dynamics_cells=[32], inverse_dropout=0.0)
    return TSIDMLoss(tsidm, beta=0.5)


def _batch(seed: int) -> TensorDict:
    g = torch.Generator().manual_seed(100 + seed)
    return TensorDict({"observation": torch.randn(BATCH, OBS, generator=g),
                       "action": torch.rand(BATCH, ACT, generator=g) * 2 - 1,
                       "next": {"observation": torch.randn(BATCH, OBS, generator=g)}}, [BATCH])


def test_stacked_tsidm_loss_equals_each_seed_alone():
    """Eq. (7) and its gradient through the stack equal each seed module's own, seed by seed."""
    losses = [_tsidm_loss(seed) for seed in (0, 1, 2)]
    stack = StackedLoss(losses)
    batches = torch.stack([_batch(k) for k in range(3)])
    out = stack(batches)
    sum_losses(out).sum().backward()
    for k, loss in enumerate(losses):
        alone = loss(batches[k])
        for key in ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym", "loss_dyn"):
            torch.testing.assert_close(out[key][k], alone[key], rtol=1e-5, atol=1e-6)
        sum_losses(alone).backward()
        for key, leaf in TensorDict.from_module(loss).items(True, True):
            if leaf.requires_grad:
                torch.testing.assert_close(stack.params.get(key).grad[k], leaf.grad, rtol=1e-4, atol=1e-6)
    # the seeds differ, so a stack that used one seed's weights for all would fail above
    assert not torch.allclose(out["ell_rec"][0], out["ell_rec"][1])


def test_stacked_value_loss_writes_back_and_keeps_frozen_leaves_frozen():
    torch.manual_seed(0)
    losses = [LatentExpectileLoss(make_latent_value(OBS, [16]), expectile=0.7) for _ in range(2)]
    for loss in losses:
        loss.make_value_estimator(gamma=0.99)
    stack = StackedLoss(losses)
    trainable = {id(t) for t in stack.trainable()}
    assert all(id(t) not in trainable for t in stack.params["target_value_network_params"].values(True, True))
    with torch.no_grad():
        for leaf in stack.trainable():
            leaf.add_(1.0)
    before = TensorDict.from_module(losses[1]).clone()
    stack.write_back()
    after = TensorDict.from_module(losses[1])
    for key, leaf in after["value_network_params"].items(True, True):
        torch.testing.assert_close(leaf, before["value_network_params"].get(key) + 1.0)
    with pytest.raises(ValueError, match="leading size 2"):
        stack(TensorDict({"latent": torch.zeros(3, 4, OBS)}, [3, 4]))


def test_seed_rng_streams_are_those_of_single_runs():
    rng = SeedRNG(2)
    rng.start(0, 7)
    rng.start(1, 8)
    torch.manual_seed(0)
    with rng.use(1):
        b1 = torch.rand(3)
    with rng.use(0):
        a1 = torch.rand(3)
    with rng.use(0):
        a2 = torch.rand(3)
    outer = torch.rand(2)  # the streams leave the outer one where it was
    torch.manual_seed(7)
    torch.testing.assert_close(torch.cat([a1, a2]), torch.rand(6), rtol=0, atol=0)
    torch.manual_seed(8)
    torch.testing.assert_close(b1, torch.rand(3), rtol=0, atol=0)
    torch.manual_seed(0)
    torch.testing.assert_close(outer, torch.rand(2), rtol=0, atol=0)


# ------------------------------------------------------------------ the recipe
# fp32 whatever the CPU: stacked (batched) and single-seed products round alike only to fp32's precision.
BASE = ["budget=smoke", "threads=1", "device=cpu", "precision=fp32", "tsidm.beta=1.0", "tsidm.steps=20",
        "tsidm.inverse_dropout=0",
        "policy.steps=40", "eval.interval=20", "eval.episodes=1", "eval.last_n=2", "eval.max_steps=30",
        "checkpoint.interval=10", "logger.log_interval=10"]


def _recipe(run_dir: Path, *overrides: str, driver: tuple | None = None) -> subprocess.CompletedProcess:
    head = [sys.executable, str(RECIPE)] if driver is None else [sys.executable, str(driver[0]), str(RECIPE),
                                                                   driver[1], driver[2]]
    return subprocess.run([*head, *BASE, f"run_dir={run_dir}", *overrides], cwd=REPO_ROOT, env=recipe_env(),
                          capture_output=True, text=True, timeout=300)


def _weights(path: Path) -> dict:
    state = torch.load(path, weights_only=True)["state_dict"]
    return {key: value for key, value in state.items() if value.is_floating_point()}


@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory) -> Path:
    """An uninterrupted ``seeds=[0,1]`` run."""
    run_dir = tmp_path_factory.mktemp("two_seeds") / "run"
    proc = _recipe(run_dir, "seeds=[0,1]")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return run_dir


@pytest.mark.slow
def test_two_seeds_in_one_process_match_their_single_seed_runs(two_seeds, tmp_path):
    """The TS-IDM and guide of each seed, and its per-seed results, match that seed's own run."""
    for seed in (0, 1):
        proc = _recipe(tmp_path / f"single{seed}", f"seed={seed}")
        assert proc.returncode == 0, proc.stderr[-2000:]
        for name in ("tsidm.pt", "policy.pt"):
            multi = _weights(two_seeds / f"seed{seed}" / name)
            single = _weights(tmp_path / f"single{seed}" / name)
            assert multi.keys() == single.keys()
            for key in single:
                torch.testing.assert_close(multi[key], single[key], rtol=0, atol=1e-5, msg=f"{name} {key}")
    zero, one = _weights(two_seeds / "seed0/policy.pt"), _weights(two_seeds / "seed1/policy.pt")
    assert any(not torch.allclose(zero[k], one[k]) for k in zero), "the seeds trained the same networks"
    summary = json.loads((two_seeds / "results.json").read_text())
    per_seed = [json.loads((two_seeds / f"seed{s}" / "results.json").read_text()) for s in (0, 1)]
    assert [r["seed"] for r in per_seed] == [0, 1]
    scores = [r["final_normalized_score_mean"] for r in per_seed]
    assert summary["final_score_mean"] == pytest.approx(sum(scores) / 2)
    assert summary["final_scores"] == {"0": pytest.approx(scores[0]), "1": pytest.approx(scores[1])}
    assert summary["seed_runs_per_hour"] > 0


@pytest.mark.slow
def test_killed_two_seed_run_resumes_bitwise(two_seeds, tmp_path):
    """SIGKILL right after a stage-1 checkpoint, then again after a stage-2 one; the twice
    resumed run equals the uninterrupted one bitwise."""
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    run_dir = tmp_path / "killed"
    killed = _recipe(run_dir, "seeds=[0,1]", driver=(driver, "kill_after_checkpoint", "tsidm,0,10"))
    assert killed.returncode == -9, killed.stderr[-2000:]
    killed = _recipe(run_dir, "seeds=[0,1]", "resume=true", driver=(driver, "kill_after_checkpoint", "policy,0,30"))
    assert killed.returncode == -9, killed.stderr[-2000:]
    assert load_training_state(run_dir / "state.pt")["step"] == 30
    resumed = _recipe(run_dir, "seeds=[0,1]", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert load_training_state(run_dir / "state.pt")["stage"] == "done"
    for seed in (0, 1):
        for name in ("tsidm.pt", "policy.pt"):
            a, b = _weights(run_dir / f"seed{seed}" / name), _weights(two_seeds / f"seed{seed}" / name)
            assert all(torch.equal(a[k], b[k]) for k in b), (seed, name)
        got = json.loads((run_dir / f"seed{seed}" / "results.json").read_text())
        want = json.loads((two_seeds / f"seed{seed}" / "results.json").read_text())
        assert [e["returns"] for e in got["evaluations"]] == [e["returns"] for e in want["evaluations"]]


@pytest.mark.parametrize("overrides, message", [
    (["seeds=[0,0]"], "must not repeat"),
    (["seeds=[]"], "non-empty list"),
    (["seeds=[0,-1]"], "integers >= 0"),
    (["seeds=[0,1]", "tsidm.beta=auto"], "tsidm.beta=auto"),
    (["seeds=[0,1]", "guide.tsym_relative=true"], "tsym_relative"),
    (["seeds=[0,1]", "domain=maze"], "guide.mode=stochastic"),
])
def test_bad_seeds_are_refused(overrides, message):
    from hydra import compose, initialize_config_dir

    from torchrl_tels.config import validate_config
    from torchrl_tels.errors import ConfigError

    with initialize_config_dir(str(REPO_ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    with pytest.raises(ConfigError, match=message):
        validate_config(cfg)


def test_bad_seeds_stop_the_recipe_before_run_dir(tmp_path):
    proc = subprocess.run([sys.executable, str(RECIPE), "budget=smoke", f"run_dir={tmp_path / 'run'}", "seeds=[0,0]"],
                          cwd=REPO_ROOT, env=recipe_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "must not repeat" in proc.stderr and proc.stderr.count("error:") == 1, proc.stderr[-1000:]
    assert not (tmp_path / "run").exists()


def test_finite_watch_names_the_seed_that_diverged():
    from torchrl_tels.training import FiniteWatch, NonFiniteLossError

    watch = FiniteWatch("stage 2 (value)", entries=["seed 3", "seed 7"])
    watch.update(TensorDict({"loss_value": torch.tensor([1.0, 2.0])}, []), 0)
    watch.update(TensorDict({"loss_value": torch.tensor([1.0, float("nan")])}, []), 1)
    watch.update(TensorDict({"loss_value": torch.tensor([float("inf"), float("nan")])}, []), 2)
    with pytest.raises(NonFiniteLossError, match=r"loss_value \(seed 7\) became nan at step 1"):
        watch.check()


def test_seeds_whose_subsets_differ_in_stage1_length_are_refused():
    from omegaconf import OmegaConf

    from torchrl_tels.errors import DatasetError
    from torchrl_tels.trainer import check_same_stage1_length

    cfg = OmegaConf.create({"tsidm": {"steps": None, "epochs": 2, "batch_size": 100}})
    assert check_same_stage1_length(cfg, [range(1000), range(950)], [0, 1]) == 20
    with pytest.raises(DatasetError, match=r"different lengths \[20, 22\]; set tsidm.steps"):
        check_same_stage1_length(cfg, [range(1000), range(1050)], [0, 1])
