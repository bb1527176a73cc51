"""Compiled and graph-captured train steps (``compile.*``) compute what the eager steps compute.

Each test builds the same stage twice from the same seed, one eager and one wrapped by
``compile_update``, feeds both the same batches, and compares every parameter after a few hundred
steps. Dropout is off, so the only difference left is float rounding in fused kernels. The CUDA-graph
variant runs where there is a GPU (``benchmarks/gpu_check.sh`` runs this file there).
"""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch._dynamo.utils import counters

from torchrl_tels.compile import capturable_adam
from torchrl_tels.config import validate_config
from torchrl_tels.data import load_dataset
from torchrl_tels.errors import ConfigError
from torchrl_tels.seeds import SeedRNG
from torchrl_tels.trainer import (compile_options, make_compiled_step, make_stage2, make_tsidm, make_tsidm_loss,
                                  StackedStage2)

from benchmarks.harness import recipe_config

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
# fp32 whatever the CPU (precision=auto would take bf16 on some), so that only the compiled kernels' rounding differs.
SMALL = ["tsidm.encoder_cells=[32]", "tsidm.decoder_cells=[32]", "tsidm.inverse_cells=[32]",
         "tsidm.action_decoder_cells=[32]", "tsidm.dynamics_cells=[32]", "value.num_cells=[32]",
         "guide.num_cells=[32]", "tsidm.inverse_dropout=0.0", "tsidm.beta=1.0", "precision=fp32"]
STEPS = 200
MODES = {"compile": ["compile.compile=true"],
         "cudagraphs": ["compile.cudagraphs=true"],
         "compile+cudagraphs": ["compile.compile=true", "compile.cudagraphs=true"]}


@pytest.fixture(scope="module")
def data():
    return load_dataset("hopper-medium-v2-10k")


def batches(data, device, n=STEPS, size=256):
    generator = torch.Generator().manual_seed(1)
    rows = data.select("observation", "action", "next")
    return [rows[torch.randint(len(data), (size,), generator=generator)].to(device) for _ in range(n)]


def stage1(cfg, data, device):
    torch.manual_seed(0)
    loss = make_tsidm_loss(cfg, make_tsidm(cfg, data).to(device), 1.0)
    optim = capturable_adam(loss.parameters(), lr=cfg.tsidm.lr, capturable=compile_options(cfg)["cudagraphs"])
    return loss, make_compiled_step(loss, optim, cfg)


def assert_same_parameters(eager, compiled, atol, rtol=1e-3):
    eager, compiled = TensorDict.from_module(eager), TensorDict.from_module(compiled)
    assert set(eager.keys(True, True)) == set(compiled.keys(True, True))
    moved = 0.0
    for key, value in eager.items(True, True):
        torch.testing.assert_close(compiled.get(key).cpu(), value.cpu(), atol=atol, rtol=rtol, msg=lambda m: f"{key}: {m}")
        moved += value.abs().sum().item()
    assert moved > 0


def compiled_graphs() -> int:
    return counters["stats"]["unique_graphs"]


def run_stage1(mode, data, device):
    eager_loss, eager_step = stage1(recipe_config([*SMALL, f"device={device}"]), data, device)
    loss, step = stage1(recipe_config([*SMALL, f"device={device}", *MODES[mode]]), data, device)
    initial = TensorDict.from_module(eager_loss).clone()
    for i, batch in enumerate(batches(data, device)):
        expected, got = eager_step(batch), step(batch)
        torch.testing.assert_close(got["loss_dyn"], expected["loss_dyn"], rtol=1e-3, atol=1e-5)
        if i == 0:
            after_first_step = compiled_graphs()
    # The first step compiled the loss once and for all: no later step recompiles it.
    assert compiled_graphs() == after_first_step
    # Training moved the weights, and the compiled step moved them to the same place.
    change = TensorDict.from_module(eager_loss) - initial
    assert max(leaf.abs().max().item() for leaf in change.values(True, True)) > 1e-3
    assert_same_parameters(eager_loss, loss, atol=1e-4)


def run_stage2(mode, data, device):
    def build(overrides):
        cfg = recipe_config([*SMALL, f"device={device}", *overrides])
        torch.manual_seed(0)
        tsidm = make_tsidm(cfg, data)
        return make_stage2(cfg, data, tsidm, action_spec=None)

    eager, compiled = build([]), build(MODES[mode])
    batch_list = [eager.buffer.sample() for _ in range(STEPS)]
    for step, batch in enumerate(batch_list):
        eager.update(batch, step)
        compiled.update(batch, step)
        if step == 0:
            after_first_step = compiled_graphs()
    assert compiled_graphs() == after_first_step
    compiled.check_finite()
    assert_same_parameters(eager.value_loss, compiled.value_loss, atol=1e-4)
    assert_same_parameters(eager.guide_loss, compiled.guide_loss, atol=1e-4)


def test_compiled_tsidm_step_matches_eager(data):
    run_stage1("compile", data, "cpu")


def test_compiled_policy_step_matches_eager(data):
    run_stage2("compile", data, "cpu")


def test_compiled_stacked_policy_step_matches_eager(data):
    """Two seeds stacked under vmap, compiled: each seed's V and guide as in the eager stacked step."""
    def build(overrides):
        cfg = recipe_config([*SMALL, *overrides])
        rng, stages = SeedRNG(2), []
        for k, seed in enumerate((4, 5)):
            rng.start(k, seed)
            with rng.use(k):
                stages.append(make_stage2(cfg, data, make_tsidm(cfg, data), action_spec=None))
        return StackedStage2(stages, rng, labels=["seed 4", "seed 5"])

    eager, compiled = build([]), build(MODES["compile"])
    for step in range(100):
        batch = eager.sample()
        eager.update(batch, step)
        compiled.update(batch, step)
    eager.write_back()
    compiled.write_back()
    for mine, theirs in zip(compiled.stages, eager.stages):
        assert_same_parameters(theirs.value_loss, mine.value_loss, atol=1e-4)
        assert_same_parameters(theirs.guide_loss, mine.guide_loss, atol=1e-4)


@cuda
@pytest.mark.parametrize("mode", ["cudagraphs", "compile+cudagraphs"])
def test_cuda_graph_steps_match_eager(mode, data):
    run_stage1(mode, data, "cuda")
    run_stage2(mode, data, "cuda")


def test_compile_switches_are_checked():
    with pytest.raises(ConfigError, match=r"compile.cudagraphs=true records CUDA graphs, but the run computes on cpu"):
        validate_config(recipe_config(["device=cpu", "compile.cudagraphs=true"]))
    with pytest.raises(ConfigError, match=r"compile.mode must be one of"):
        validate_config(recipe_config(["compile.mode=fastest"]))
    with pytest.raises(ConfigError, match=r"compile.compile must be true or false, got 'yes'"):
        validate_config(recipe_config(["compile.compile=yes"]))


def test_compiled_policy_on_device_acts_as_the_policy():
    """The evaluation policy's compiled call (compile_options of PolicyOnDevice) writes the policy's
    actions into the step, and nothing else."""
    from tensordict.nn import TensorDictModule
    from torchrl.modules import MLP

    from torchrl_tels.envs import PolicyOnDevice

    net = torch.nn.Sequential(MLP(in_features=11, out_features=3, num_cells=[64, 64]), torch.nn.Tanh())
    policy = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
    compiled = PolicyOnDevice(policy, "cpu", "cpu", compile=True)
    for _ in range(3):
        observation = torch.randn(10, 11)
        step = compiled(TensorDict({"observation": observation, "step_count": torch.ones(10, 1)}, [10]))
        assert set(step.keys()) == {"observation", "step_count", "action"}
        torch.testing.assert_close(step["action"], net(observation), rtol=1e-5, atol=1e-6)
