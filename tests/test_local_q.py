"""``study.local_q``: the rows the return Q may fit, its held-out episodes, and a learning test
where the return is a known function of state and action."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from study import local_q, value_delivery


def _episodes(lengths, terminated, seed=0):
    """Episodes one after another, observations and actions uniform in [-1, 1]; the reward of a row is
    obs₀ + 2·a₀ − a₁², so a one-step return is a known function of (s, a)."""
    generator = torch.Generator().manual_seed(seed)
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    ends = torch.cat([episode[1:] != episode[:-1], torch.tensor([True])])
    terminal = torch.zeros(len(episode), dtype=torch.bool)
    terminal[ends.nonzero().flatten()[torch.tensor(terminated)]] = True
    observation = torch.rand(len(episode), 4, generator=generator) * 2 - 1
    action = torch.rand(len(episode), 2, generator=generator) * 2 - 1
    reward = observation[:, :1] + 2 * action[:, :1] - action[:, 1:] ** 2
    return TensorDict({"episode": episode, "observation": observation, "action": action,
                       "next": {"reward": reward, "done": ends.unsqueeze(-1), "terminated": terminal.unsqueeze(-1)}},
                      batch_size=[len(episode)])


def test_known_returns_are_the_rows_a_whole_horizon_or_a_termination_away():
    data = _episodes([5, 3, 4], terminated=[False, True, False])
    # episode 0 times out: only rows with at least 3 more rows after them count (one row more than the return
    # needs); episode 1 terminates: all rows; episode 2 is cut: as episode 0
    expected = [True, True, False, False, False] + [True] * 3 + [True, False, False, False]
    assert value_delivery.known_returns(data, 3).tolist() == expected


def test_held_out_episodes_are_whole_episodes_never_none_and_never_all():
    data = _episodes([3] * 20, terminated=[True] * 20)
    held_out = local_q.held_out_episodes(data, 0.1)
    assert held_out.sum() == 6  # two whole episodes of three rows
    for episode in data["episode"].unique():
        rows = held_out[data["episode"] == episode]
        assert rows.all() or not rows.any()
    assert local_q.held_out_episodes(data, 0.0).sum() == 3 and local_q.held_out_episodes(data, 1.0).sum() == 57
    with pytest.raises(ValueError, match="1 episode"):
        local_q.held_out_episodes(_episodes([5], terminated=[True]), 0.1)


def test_the_return_q_learns_a_known_return_and_orders_one_states_actions():
    torch.set_num_threads(1)
    data = _episodes([1] * 4000, terminated=[True] * 4000)  # one-step episodes: the return is the reward
    q, fitted = local_q.fit_return_q(data, gamma=0.99, horizon=1, steps=1500)
    assert fitted["rows"] + fitted["held_out_rows"] == 4000 and fitted["held_out_rows"] == 400
    assert fitted["held_out_rank"] > 0.95
    # one state, many actions: Q's order is the reward's, which the state does not enter
    action = torch.rand(64, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    state = torch.full((64, 4), 0.3)
    truth = 0.3 + 2 * action[:, 0] - action[:, 1] ** 2
    rank = local_q.row_spearman(q(state, action).unsqueeze(0), truth.unsqueeze(0)).item()
    assert rank > 0.9
    # in the return's own units, not only in order: the standardization is undone
    assert (q(state, action) - truth).abs().mean() < 0.1 * truth.std()
    # and an untrained Q does not: the test can fail
    q0, _ = local_q.fit_return_q(data, gamma=0.99, horizon=1, steps=0)
    assert abs(local_q.row_spearman(q0(state, action).unsqueeze(0), truth.unsqueeze(0)).item()) < 0.9


def test_the_table_puts_the_return_q_under_its_columns_and_dashes_where_a_record_has_none():
    old = {"final_score": 40.0, "iql_score": 50.0, "q_rank": 0.12}
    gain = lambda median, share: {"median": median, "mean": median, "share_positive": share}
    new = old | {"horizon": 300, "return_q": {"held_out_rank": 0.81, "rank": 0.07,
                                              "chosen_gain": gain(-1.5, 0.25), "best_gain": gain(30.0, 0.9)}}
    text = local_q.table({("arm", "task", 0): old, ("arm", "task", 1): new})
    header, rule, *rows = text.splitlines()
    names = header.strip("| ").split(" | ")
    assert len(names) == rule.count("---")
    cells = [dict(zip(names, row.strip("| ").split(" | "))) for row in rows]
    assert cells[0]["horizon"] == str(value_delivery.HORIZON) and cells[0]["return Q: rank with the return after"] == "—"
    assert cells[1]["horizon"] == "300" and cells[1]["return Q: held-out rank across states"] == "0.81"
    assert cells[1]["return Q: rank with the return after"] == "0.07"
    assert cells[1]["return gain of the return Q's first step"] == "-1.5 (25%)"
    assert cells[1]["of the best candidate's"] == "+30.0 (90%)"


def test_the_return_q_fits_only_rows_whose_whole_horizon_the_data_records():
    torch.set_num_threads(1)
    lengths, terminated = [8] * 30, [k % 2 == 0 for k in range(30)]  # every other episode times out
    data = _episodes(lengths, terminated=terminated)
    _, fitted = local_q.fit_return_q(data, gamma=0.9, horizon=3, steps=0)
    # a terminated episode: all 8 rows; a timed-out one: the 5 rows with at least 3 rows after them
    held_out = local_q.held_out_episodes(data, local_q.HELD_OUT)
    per_episode = torch.tensor([8 if t else 5 for t in terminated])
    held = torch.tensor([bool(held_out[data["episode"] == k].any()) for k in range(30)])
    assert (fitted["rows"], fitted["held_out_rows"]) == (int(per_episode[~held].sum()), int(per_episode[held].sum()))
    assert fitted["steps"] == 0
