"""Where a run computes: the device and thread settings, and the checks that need no host sync.

The CUDA tests skip on a machine without a GPU; ``benchmarks/gpu_check.sh`` runs them on one.
"""
from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_tels.config import ConfigError, resolve_device, resolve_threads
from torchrl_tels.modules import TSIDM
from torchrl_tels.objectives import TSIDMLoss
from torchrl_tels.training import FiniteWatch, NonFiniteLossError

REPO_ROOT = Path(__file__).resolve().parents[1]
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def test_device_names():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "cuda:x", "CPU", "mps:0"):
        with pytest.raises(ConfigError, match=r"device must be auto, cpu, cuda or cuda:N, got"):
            resolve_device(bad)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_cuda_refused_without_a_gpu():
    with pytest.raises(ConfigError, match=r"device=cuda:1 but this machine has no CUDA device"):
        resolve_device("cuda:1")


def test_thread_setting():
    assert resolve_threads("auto") == max(1, len(os.sched_getaffinity(0)) // 2)  # the CPUs this process may use
    assert resolve_threads(None) == resolve_threads("auto")
    assert resolve_threads(3) == 3


def _losses(value: float) -> TensorDict:
    return TensorDict({"loss_a": torch.tensor(1.0), "loss_b": torch.tensor(value), "ell_x": torch.tensor(float("nan"))}, [])


def test_finite_watch_names_the_first_bad_term_and_step():
    watch = FiniteWatch("stage X")
    for step in range(5):
        watch.update(_losses(2.0), step)
    watch.check()  # finite so far; ell_* entries are not losses and are not watched
    watch.update(_losses(float("inf")), 5)
    watch.update(_losses(float("nan")), 6)
    with pytest.raises(NonFiniteLossError, match=r"^stage X: loss_b became inf at step 5; the run stops here"):
        watch.check()


def _batch(n=64, device="cpu"):
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, 11, generator=g)
    td = TensorDict({"observation": obs, "action": torch.rand(n, 3, generator=g) * 2 - 1,
                     ("next", "observation"): obs + 0.1 * torch.randn(n, 11, generator=g)}, [n])
    return td.to(device)


@cuda
def test_tsidm_loss_on_cuda_matches_cpu():
    torch.manual_seed(0)
    tsidm = TSIDM(11, 3, inverse_dropout=None)
    cpu = TSIDMLoss(tsidm, beta=1.0)(_batch())
    gpu = TSIDMLoss(copy.deepcopy(tsidm).cuda(), beta=1.0)(_batch(device="cuda"))
    for key in ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym"):
        torch.testing.assert_close(gpu[key].cpu(), cpu[key], rtol=1e-3, atol=1e-5)


@cuda
def test_recipe_runs_on_cuda_and_its_files_load_on_the_cpu(tmp_path):
    run_dir = tmp_path / "run"
    subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "tels_offline.py"), "budget=smoke", "device=cuda",
                    f"run_dir={run_dir}", "logger.wandb_mode=disabled"], check=True, cwd=REPO_ROOT)
    results = json.loads((run_dir / "results.json").read_text())
    assert len(results["evaluations"]) == 2
    tsidm = TSIDM.load(run_dir / "tsidm.pt", observation_dim=11, action_dim=3)
    assert next(tsidm.parameters()).device == torch.device("cpu")


@cuda
def test_batched_evaluation_of_a_cuda_policy_matches_the_cpu():
    """A policy on the GPU evaluated in CPU envs stepped together, whose copies fall at different steps:
    the returns of the same policy on the CPU."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import DoubleToFloat, TransformedEnv
    from torchrl.modules import MLP

    from torchrl_tels.envs import evaluate_policy, make_eval_envs

    torch.manual_seed(0)
    net = torch.nn.Sequential(MLP(in_features=11, out_features=3, num_cells=[64, 64]), torch.nn.Tanh())
    gpu_net = copy.deepcopy(net).cuda()
    cpu = TensorDictModule(lambda obs: 0.05 * net(obs), in_keys=["observation"], out_keys=["action"])
    gpu = TensorDictModule(lambda obs: 0.05 * gpu_net(obs), in_keys=["observation"], out_keys=["action"])
    gpu.register_module("net", gpu_net)  # so that the policy reports the device it computes on
    batch = make_eval_envs("Hopper-v4", 4, wrap=lambda env: TransformedEnv(env, DoubleToFloat()))
    on_cpu, lengths = evaluate_policy(cpu, batch, 4, seed=3, max_steps=200, with_lengths=True)
    on_gpu = evaluate_policy(gpu, batch, 4, seed=3, max_steps=200)
    assert max(lengths) < 200 and len(set(lengths)) > 1  # the path that merges finished and running copies
    torch.testing.assert_close(torch.tensor(on_gpu), torch.tensor(on_cpu), rtol=1e-3, atol=1e-3)


def test_bf16_autocast_follows_the_run_device():
    """precision=bf16 autocasts on the device the run computes on, not always on the CPU."""
    from omegaconf import OmegaConf

    from torchrl_tels.trainer import autocast

    cfg = OmegaConf.create({"device": "cpu", "precision": "bf16"})
    assert autocast(cfg).device == "cpu" and autocast(cfg)._enabled
    assert not autocast(OmegaConf.create({"device": "cpu", "precision": "fp32"}))._enabled
    if torch.cuda.is_available():
        assert autocast(OmegaConf.create({"device": "cuda", "precision": "bf16"})).device == "cuda"


@cuda
def test_stacked_seeds_on_cuda_match_cpu():
    """Several seeds in one process on the GPU: the stacked Eq. (7) equals the CPU's."""
    from torchrl_tels.seeds import StackedLoss

    losses = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        losses.append(TSIDMLoss(TSIDM(6, 2, encoder_cells=[32], decoder_cells=[32], inverse_cells=[32],
                                      action_decoder_cells=[32], dynamics_cells=[32], inverse_dropout=0.0)))
    batch = TensorDict({"observation": torch.randn(2, 64, 6), "action": torch.rand(2, 64, 2) * 2 - 1,
                        "next": {"observation": torch.randn(2, 64, 6)}}, [2, 64])
    on_cpu = StackedLoss(losses)(batch)
    on_gpu = StackedLoss([copy.deepcopy(loss).cuda() for loss in losses])(batch.cuda())
    for key in ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym"):
        torch.testing.assert_close(on_gpu[key].cpu(), on_cpu[key], rtol=1e-4, atol=1e-5)


def test_auto_precision_is_bf16_only_on_a_cpu_that_multiplies_it_natively(monkeypatch):
    import torchrl_tels.config as config

    for native in (True, False):
        monkeypatch.setattr(config, "native_bf16_supported", lambda: native)
        assert config.resolve_precision("auto", "cpu") == ("bf16" if native else "fp32")
        assert config.resolve_precision("fp32", "cpu") == "fp32"  # an explicit choice is kept
        assert config.resolve_precision("bf16", "cpu") == "bf16"
    if torch.cuda.is_available():
        assert config.resolve_precision("auto", "cuda") == "fp32"
