"""What would a perfect value gain from choosing among one step's alternatives?

    python -m study.oracle_choice --run-dir <run> --name <arm>-<task>-seed<k>
    python -m study.oracle_choice --table

``model_selection`` found that V cannot order the candidates near the actor's latent action by the return
that follows them, although the simulator makes that return predictable. This reading bounds what a value
that could would gain. The oracle acts like ``model_selection``'s chooser, with the same ``CANDIDATES`` latent
actions around the actor's own, but ranks them by the truth: from the simulator's exact state, each candidate's
action, then the actor for ``LOOKAHEAD`` - 1 steps, and it acts the candidate of largest discounted return
(the actor's own, k = 0, is a candidate, so within the lookahead the oracle is never behind the actor). This
is one step of policy iteration by simulator rollouts around the TELS actor: the most any choice among these
candidates by any value of that horizon can deliver.

Read over the first ``STEPS`` steps of ``EPISODES`` episodes, reset alike for the actor and the oracle: the
undiscounted return of each (the paired change and how many episodes are up), how many steps each lasted
(a fall ends the window early), and the share of decisions where the oracle's choice is not the actor's own. The window keeps the oracle affordable: each of its steps costs ``CANDIDATES`` ×
``LOOKAHEAD`` simulator steps.

If the oracle gains much, the candidates hold an improvement and a value with that resolution is what TELS
lacks; if it gains little, no value can rescue a choice this local.

Writes ``study/results/oracle_choice/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import statistics

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from benchmarks.harness import REPO
from study.latent_scale import run_results
from study.model_selection import candidate_policies, CANDIDATES, own_action
from study.proposal_cap import load_finished_run, reading_main
from study.value_delivery import discounted_returns, run_config
from torchrl_tels.trainer import make_data

RESULTS = REPO / "study" / "results" / "oracle_choice"
COMMAND = "python -m study.oracle_choice"
LOOKAHEAD = 100
EPISODES = 3
STEPS = 300
SEED = 7_000


class LookaheadOracle:
    """Ranks candidate actions by the discounted return of ``lookahead`` simulator steps from an exact state:
    the candidate's action first, then ``policy`` (a batch of observations → actions)."""

    def __init__(self, env_id: str, policy, count: int, lookahead: int, gamma: float):
        self.envs = [gym.make(env_id).unwrapped for _ in range(count)]
        for seed, env in enumerate(self.envs):
            env.reset(seed=seed)
        self.policy, self.lookahead, self.gamma = policy, lookahead, gamma

    def returns(self, qpos: np.ndarray, qvel: np.ndarray, observation: torch.Tensor,
                first_actions: torch.Tensor) -> torch.Tensor:
        """``(candidates,)``: the discounted return after each of ``first_actions`` from the state (qpos, qvel),
        which ``observation`` describes; an episode that terminates stops there."""
        envs = self.envs[:len(first_actions)]
        for env in envs:
            env.set_state(qpos, qvel)
        return discounted_returns(envs, observation.expand(len(envs), -1), self.policy, self.lookahead,
                                  self.gamma, first_actions)

    def close(self) -> None:
        for env in self.envs:
            env.close()


def play_episode(env_id: str, seed: int, act, steps: int) -> tuple[float, int]:
    """The undiscounted return and the length of one episode of ``env_id`` reset with ``seed``, cut after
    ``steps`` steps; ``act(env, observation)`` → action."""
    env = gym.make(env_id)
    try:
        observation, _ = env.reset(seed=seed)
        total, length, done = 0.0, 0, False
        while not done and length < steps:
            observation, reward, terminated, truncated, _ = env.step(act(env, observation))
            total, length, done = total + float(reward), length + 1, terminated or truncated
    finally:
        env.close()
    return total, length


def oracle_choice(run_dir, lookahead: int | None = None, episodes: int | None = None,
                  steps: int | None = None) -> dict:
    lookahead = LOOKAHEAD if lookahead is None else lookahead
    episodes = EPISODES if episodes is None else episodes
    steps = STEPS if steps is None else steps
    run = load_finished_run(run_dir, episodes=1)
    cfg = run_config(run_dir)
    data, _ = make_data(cfg)  # the rows model_selection draws σ from
    gamma = float(cfg.value.gamma)
    chooser = candidate_policies(run, data)(own_action)
    oracle = LookaheadOracle(run.task.env_id, chooser.own_actions, CANDIDATES, lookahead, gamma)
    departures = []

    def actor(env, observation):
        return chooser.own_actions(torch.as_tensor(observation, dtype=torch.float32)[None])[0].numpy()

    def by_oracle(env, observation):
        observation = torch.as_tensor(observation, dtype=torch.float32)[None]
        _, latent_actions, _ = chooser.candidates(observation)
        actions = chooser.actions(latent_actions)[:, 0]  # (candidates, action)
        state = env.unwrapped.data
        best = int(oracle.returns(state.qpos.copy(), state.qvel.copy(), observation, actions).argmax())
        departures.append(best != 0)
        return actions[best].numpy()

    returns, lengths = {"actor": [], "oracle": []}, {"actor": [], "oracle": []}
    try:
        for episode in tqdm(range(episodes), desc=f"oracle episodes ({lookahead}-step lookahead)"):
            seed = SEED + run.seed + episode
            for name, act in (("actor", actor), ("oracle", by_oracle)):
                episode_return, length = play_episode(run.task.env_id, seed, act, steps)
                returns[name].append(episode_return)
                lengths[name].append(length)
    finally:
        oracle.close()
    changes = [o - a for o, a in zip(returns["oracle"], returns["actor"])]
    return {"final_score": run.results["final_normalized_score_mean"], "gamma": gamma, "candidates": CANDIDATES,
            "lookahead": lookahead, "episodes": episodes, "steps": steps, "returns": returns, "lengths": lengths,
            "change": {"mean": statistics.mean(changes), "up": sum(c > 0 for c in changes)},
            "departure_share": float(np.mean(departures)), "decisions": len(departures)}


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    """One row per reading (``{(arm, task, seed): record}``), in task, lookahead, arm and seed order."""
    records = run_results(RESULTS) if records is None else records
    lines = ["| arm | task | seed | run's score | lookahead | episodes | return over the window: actor, oracle "
             "| paired change (episodes up) | steps lasted: actor, oracle | oracle departs from the actor |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    order = lambda item: (item[0][1], item[1]["lookahead"], item[0][0], item[0][2])
    for (arm, task, seed), r in sorted(records.items(), key=order):
        returns, lengths, change = r["returns"], r["lengths"], r["change"]
        lines.append(
            f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r['lookahead']} | {r['episodes']} "
            f"| {statistics.mean(returns['actor']):.0f}, {statistics.mean(returns['oracle']):.0f} "
            f"| {change['mean']:+.0f} ({change['up']} of {r['episodes']}) "
            f"| {statistics.median(lengths['actor']):.0f}, {statistics.median(lengths['oracle']):.0f} "
            f"| {r['departure_share']:.0%} |")
    return "\n".join(lines + ["", *pooled_changes(records)])


def pooled(records: dict[tuple[str, str, int], dict]) -> dict[tuple[str, int], tuple[float, float, int, int]]:
    """``{(task, lookahead): (change, change over the actor's return, episodes up, episodes)}``: per task and
    lookahead, over every seed's episodes, the mean paired change of the window's return from the actor's."""
    groups: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for (_, task, _), r in sorted(records.items()):
        pairs = groups.setdefault((task, r["lookahead"]), [])
        pairs += zip(r["returns"]["actor"], r["returns"]["oracle"])
    out = {}
    for key, pairs in sorted(groups.items()):
        change = statistics.mean(o - a for a, o in pairs)
        out[key] = (change, change / statistics.mean(a for a, _ in pairs), sum(o > a for a, o in pairs), len(pairs))
    return out


def pooled_changes(records: dict[tuple[str, str, int], dict]) -> list[str]:
    """:func:`pooled` as the lines under the table."""
    return [f"- {task}, lookahead {lookahead}: oracle over actor {change:+.0f} "
            f"({relative:+.0%} of the actor's return), up on {up} of {n} episodes."
            for (task, lookahead), (change, relative, up, n) in pooled(records).items()]


def _summary(record: dict) -> str:
    returns = record["returns"]
    return (f"{record['steps']}-step return: actor {statistics.mean(returns['actor']):.0f}, oracle "
            f"{statistics.mean(returns['oracle']):.0f} ({record['change']['mean']:+.0f}); the oracle departs from "
            f"the actor on {record['departure_share']:.0%} of decisions")


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=oracle_choice,
                 table=table, summary=_summary,
                 options={"lookahead": {"type": int, "help": f"simulator steps per ranking (default {LOOKAHEAD})"}})


if __name__ == "__main__":
    main()
