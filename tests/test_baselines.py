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
    data = _episodes([[1.0, 2.0, 3.0], [-1.0, 0.0], [10.0, 0.5]])
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
    data = _episodes([[1.0, 2.0], [4.0, 0.0]])  # returns 3 and 4
    scaled, scale = baselines._scale_rewards(data, {"reward_scale": "return_range", "reward_bias": 0.0})
    assert scale == pytest.approx(1000.0)
    torch.testing.assert_close(scaled["next", "reward"], data["next", "reward"] * 1000.0)
    assert scaled is not data and data["next", "reward"][0].item() == 1.0  # the caller's data is left alone
    shifted, scale = baselines._scale_rewards(data, {"reward_scale": 1.0, "reward_bias": -1.0})
    torch.testing.assert_close(shifted["next", "reward"], data["next", "reward"] - 1.0)
    same, scale = baselines._scale_rewards(data, {"reward_scale": 1.0, "reward_bias": 0.0})
    assert same is data and scale == 1.0
    for bad in (0, -2.0, float("inf"), "returns", True):
        with pytest.raises(ValueError, match="reward_scale must be"):
            baselines._scale_rewards(data, {"reward_scale": bad})
    with pytest.raises(ValueError, match="different returns"):
        baselines._scale_rewards(_episodes([[1.0, 0.0], [0.5, 0.5]]), {"reward_scale": "return_range"})
    with pytest.raises(ValueError, match="never both"):
        baselines._scale_rewards(data, {"reward_scale": 2.0, "reward_bias": -1.0})
    with pytest.raises(ValueError, match="'episode' ids"):
        baselines.return_range_scale(data.exclude("episode"))


def test_one_transition_pieces_do_not_set_the_return_range():
    # the middle piece is a lone transition with return -50; without it the spread is 12 - 2
    data = _episodes([[1.0, 1.0], [-50.0], [6.0, 6.0]])
    assert baselines.return_range_scale(data) == pytest.approx(100.0)


def test_halfcheetah_scale_spans_whole_episodes():
    # the shared halfcheetah 10k file holds 998-step episodes, each followed by a one-step piece
    data = load_dataset("halfcheetah-medium-v2-10k")
    episode = data["episode"]
    long_returns = [data["next", "reward"][episode == e].sum().item() for e in episode.unique()
                    if (episode == e).sum() > 1]
    assert len(long_returns) >= 5 and min(long_returns) > 1000  # whole episodes of a medium policy
    expected = 1000.0 / (max(long_returns) - min(long_returns))
    assert baselines.return_range_scale(data) == pytest.approx(expected, rel=1e-6)


def test_run_grid_set_reads_values_as_yaml_and_names_bad_keys(tmp_path, capsys):
    task, own = "hopper-medium-v2-10k", ["--results-dir", str(tmp_path)]
    args = run_grid.parse_args(["--method", "iql", "--task", task, "--seed", "0", "--set", "reward_scale=return_range",
                                "--set", "temperature=10", "--set", "lr=3e-4", *own])
    assert args.set == {"reward_scale": "return_range", "temperature": 10, "lr": 3e-4}
    command = run_grid.one_command(args, "iql", task, 0)
    assert "--set=reward_scale=return_range" in command
    # the command a result records gives the same values back
    again = run_grid.parse_args(command[3:])
    assert again.set == args.set and isinstance(again.set["lr"], float)
    for argv, message in ((["--method", "bc", "--set", "expectile=0.9", *own], "bc has no hyperparameter(s) ['expectile']"),
                          (["--method", "tels", "--set", "lr=1", *own], "--set applies to the baselines only"),
                          (["--method", "iql", "--set", "expectile", *own], "--set takes KEY=VALUE"),
                          (["--method", "iql", "--set", "reward_scale=0", *own], "finite positive number"),
                          (["--method", "iql", "--set", "lr=1"], "need their own --results-dir")):
        with pytest.raises(SystemExit):
            run_grid.parse_args([*argv, "--task", task, "--seed", "0"])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_grid.parse_args(["--method", "iql", "--task", "antmaze-umaze-v0-10k", "--seed", "0",
                             "--set", "reward_scale=return_range", *own])
    assert "mazes take the IQL paper's r - 1" in capsys.readouterr().err


def test_run_one_hands_the_set_values_to_the_baseline_over_the_maze_ones(tmp_path, monkeypatch):
    received = {}

    def fake_train_baseline(method, task, **kwargs):
        received[task] = kwargs["hyperparameters"]
        return {"final_normalized_score_mean": 0.0, "torch_threads": 1, "budget": {}}

    monkeypatch.setattr(run_grid, "train_baseline", fake_train_baseline)
    for task in ("hopper-medium-v2-10k", "antmaze-umaze-v0-10k"):
        args = run_grid.parse_args(["--method", "iql", "--task", task, "--seed", "0", "--steps", "10",
                                    "--set", "temperature=5", "--results-dir", str(tmp_path)])
        run_grid.run_one("iql", task, 0, args)
    assert received["hopper-medium-v2-10k"] == {"temperature": 5}
    assert received["antmaze-umaze-v0-10k"] == {**baselines.MAZE_HYPERPARAMETERS["iql"], "temperature": 5}


# ----------------------------------------------------------- IQL's authors' actor
def _box(dim: int):
    from torchrl.data import Bounded

    return Bounded(-torch.ones(dim), torch.ones(dim), (dim,))


def test_authors_actor_is_a_gaussian_around_a_tanh_mean_with_a_free_log_std():
    hp = {**baselines.HYPERPARAMETERS["iql"], **baselines.IQL_AUTHORS_ACTOR}
    actor = baselines._tanh_mean_gaussian_actor("observation", 5, _box(3), hp)
    obs = torch.randn(7, 5)
    dist = actor.get_dist(TensorDict(observation=obs, batch_size=[7]))
    mlp = actor.module[0].module[0]  # the MLP before the tanh
    torch.testing.assert_close(dist.mean, torch.tanh(mlp(obs)))  # the box is [-1, 1]: tanh is the mean
    log_std = actor.module[0].module[2].module.state_independent_scale
    torch.testing.assert_close(dist.stddev, log_std.exp().expand(7, 3))
    with torch.no_grad():
        log_std.fill_(-9.0)  # below the authors' floor of -5
    dist = actor.get_dist(TensorDict(observation=obs, batch_size=[7]))
    torch.testing.assert_close(dist.stddev, torch.full((7, 3), torch.tensor(-5.0).exp().item()))
    # samples are not squashed: a Gaussian's log-likelihood of +-1 is finite
    assert torch.isfinite(dist.log_prob(torch.ones(7, 3))).all()


def test_authors_actor_learns_saturated_actions_by_likelihood():
    """Actions at the box's edge, as 30 % of the maze data's entries: the tanh-mean Gaussian fits them."""
    torch.manual_seed(0)
    hp = {**baselines.HYPERPARAMETERS["iql"], **baselines.IQL_AUTHORS_ACTOR}
    actor = baselines._tanh_mean_gaussian_actor("observation", 4, _box(2), hp)
    obs = torch.randn(256, 4)
    target = torch.stack([torch.sign(obs[:, 0]), 0.5 * torch.tanh(obs[:, 1])], -1)  # first entry always +-1
    target = baselines._clip_actions(TensorDict(action=target, batch_size=[256]), _box(2), 1e-5)["action"]
    assert target.abs().max() == pytest.approx(1 - 1e-5)
    optim = torch.optim.Adam(actor.parameters(), lr=3e-3)
    for _ in range(400):
        loss = -actor.get_dist(TensorDict(observation=obs, batch_size=[256])).log_prob(target).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    mean = actor.get_dist(TensorDict(observation=obs, batch_size=[256])).mean
    assert (mean[:, 0] - target[:, 0]).abs().median() < 0.05
    assert (mean[:, 1] - target[:, 1]).abs().median() < 0.05


def test_authors_actor_lr_follows_a_cosine_decay():
    import math

    optim = torch.optim.Adam([torch.nn.Parameter(torch.zeros(2))], lr=3e-4)
    schedule = baselines.cosine_decay(optim, horizon=8)
    lrs = []
    for _ in range(10):
        optim.step()
        schedule.step()
        lrs.append(optim.param_groups[0]["lr"])
    assert lrs == pytest.approx([3e-4 * 0.5 * (1 + math.cos(math.pi * min(k, 8) / 8)) for k in range(1, 11)])
    assert lrs[-1] == 0.0


def test_td3bc_reports_both_terms_every_step_and_updates_the_actor_every_other():
    """The NaN watch stacks a fixed set of terms: a TD3+BC step without an actor update still reports one."""
    data = load_dataset("hopper-medium-v2-10k")[:512]
    actor, update, loss = baselines._build_td3bc("observation", 11, _box(3), baselines.HYPERPARAMETERS["td3bc"])
    actor_params = lambda: [p.detach().clone() for p in loss.actor_network_params.values(True, True)]
    before = actor_params()
    reported = []
    for step in range(4):
        losses = update(data[step * 64:(step + 1) * 64], step)
        assert set(losses.keys()) == {"loss_qvalue", "loss_actor"}
        reported.append(losses["loss_actor"].item())
        after = actor_params()
        moved = any(not torch.equal(a, b) for a, b in zip(before, after))
        assert moved == (step % 2 == 0)  # policy_update_delay 2
        before = after
    assert reported[1] == reported[0] and reported[3] == reported[2] and reported[2] != reported[0]
    from torchrl_tels.training import FiniteWatch

    watch = FiniteWatch("TD3+BC")
    watch.update(update(data[:64], 4), 4)
    watch.update(update(data[:64], 5), 5)
    watch.check()
