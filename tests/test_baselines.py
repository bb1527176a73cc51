"""The baselines' reward scale: the IQL paper's ``1000 / (max - min)`` of episode returns, and ``run_grid --set``."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from benchmarks import baselines, run_grid
from torchrl_tels.data import load_dataset


def _episodes(rewards: list[list[float]]) -> TensorDict:
    episode = torch.cat([torch.full((len(r),), i) for i, r in enumerate(rewards)])
    reward = torch.tensor([x for r in rewards for x in r]).unsqueeze(-1)
    return TensorDict({"episode": episode, ("next", "reward"): reward}, batch_size=[len(episode)])


def test_return_range_scale_is_1000_over_the_spread_of_episode_returns():
    # returns 6, -1 and 10.5: the spread is 11.5
    data = _episodes([[1.0, 2.0, 3.0], [-1.0], [10.0, 0.5]])
    assert baselines.return_range_scale(data) == pytest.approx(1000.0 / 11.5)
    # episode ids need not be contiguous
    data["episode"] = data["episode"] * 7 + 3
    assert baselines.return_range_scale(data) == pytest.approx(1000.0 / 11.5)


def test_return_range_scale_of_a_shared_set_matches_a_loop_over_its_episodes():
    data = load_dataset("hopper-medium-v2-10k")
    returns: dict[int, float] = {}
    for ep, r in zip(data["episode"].tolist(), data["next", "reward"].reshape(-1).tolist()):
        returns[ep] = returns.get(ep, 0.0) + r
    expected = 1000.0 / (max(returns.values()) - min(returns.values()))
    assert baselines.return_range_scale(data) == pytest.approx(expected, rel=1e-6)


def test_rewards_are_scaled_then_shifted_and_bad_settings_are_refused():
    data = _episodes([[1.0, 2.0], [4.0]])
    scaled, scale = baselines._scale_rewards(data, {"reward_scale": "return_range", "reward_bias": -1.0})
    assert scale == pytest.approx(1000.0)
    torch.testing.assert_close(scaled["next", "reward"], data["next", "reward"] * 1000.0 - 1.0)
    assert scaled is not data and data["next", "reward"][0].item() == 1.0  # the caller's data is left alone
    same, scale = baselines._scale_rewards(data, {"reward_scale": 1.0, "reward_bias": 0.0})
    assert same is data and scale == 1.0
    for bad in (0, -2.0, "returns", True):
        with pytest.raises(ValueError, match="reward_scale must be"):
            baselines._scale_rewards(data, {"reward_scale": bad})
    with pytest.raises(ValueError, match="different returns"):
        baselines._scale_rewards(_episodes([[1.0], [1.0]]), {"reward_scale": "return_range"})


def test_run_grid_set_reads_values_as_yaml_and_names_bad_keys(capsys):
    task = "hopper-medium-v2-10k"
    args = run_grid.parse_args(["--method", "iql", "--task", task, "--seed", "0", "--set", "reward_scale=return_range",
                                "--set", "temperature=10"])
    assert args.set == {"reward_scale": "return_range", "temperature": 10}
    assert "--set=reward_scale=return_range" in run_grid.one_command(args, "iql", task, 0)
    for argv, message in ((["--method", "bc", "--set", "expectile=0.9"], "bc has no hyperparameter(s) ['expectile']"),
                          (["--method", "tels", "--set", "lr=1"], "--set applies to the baselines only"),
                          (["--method", "iql", "--set", "expectile"], "--set takes KEY=VALUE")):
        with pytest.raises(SystemExit):
            run_grid.parse_args([*argv, "--task", task, "--seed", "0"])
        assert message in capsys.readouterr().err
