"""Does a Q, IQL's or one fitted to the data's returns, order one step's alternatives where TELS's V does not?

    python -m study.local_q --run-dir <run> --name <arm>-<task>-seed<k> [--horizon H]
    python -m study.local_q --table

``model_selection`` reads, from a TELS run's start states, how well V at the state each of ``CANDIDATES``
first actions reaches ranks the discounted return that follows (each candidate's action, then the actor).
Low there, the question is whether value learning on these few transitions fails at this in general, or
TELS's V (a state value in the TS-IDM's latent space) in particular. This reading trains IQL
(:func:`benchmarks.baselines.train_baseline`, torchrl's ``IQLLoss`` and its offline config) on the run's own
training transitions for ``IQL_STEPS`` steps and reads, on the same states, candidates and returns, the
rank correlation of min(Q₁, Q₂)(s, a) with the return after (``q_rank``). IQL's own score, from its final
evaluation, says what this Q does as a policy.

IQL's Q, like V, learns the long run by bootstrapping one step at a time. ``oracle_choice`` finds that what
decides which candidate is better is often a fall hundreds of steps later. The second Q here is fitted
without bootstrapping: a regression of the data's own discounted return over the next ``horizon`` steps
(:func:`fit_return_q`, Monte-Carlo targets of the behaviour policy, which the near-BC actor resembles), the
same target the return after each candidate is read over. ``return_q`` reports its rank correlation with the
data's returns on episodes it was not fitted to (``held_out_rank``: does it order states?), its local rank
with the return after (``rank``: does it order one state's actions?), and the return gained by acting
its choice among the candidates for the first step (``chosen_gain``), against the best candidate's gain
(``best_gain``, the one-step oracle's), both over the actor's own.

Writes ``study/results/local_q/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

from benchmarks.baselines import train_baseline
from benchmarks.harness import REPO
from study.latent_scale import run_results
from study.model_selection import (CANDIDATES, HORIZON_OPTION, local_returns, own_action,
                                   row_spearman, start_candidates, summary_of)
from study.proposal_cap import EPISODES, load_finished_run, reading_main
from study.value_delivery import HORIZON, known_returns, recorded_returns, run_config
from torchrl_tels.trainer import make_data

RESULTS = REPO / "study" / "results" / "local_q"
COMMAND = "python -m study.local_q"
IQL_STEPS = 20_000
RETURN_Q_STEPS = 10_000
RETURN_Q_BATCH = 256
HELD_OUT = 0.1  # the share of the data's episodes the return Q is not fitted to


@torch.no_grad()
def min_q(loss, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """IQL's min(Q₁, Q₂)(s, a), as its policy and value updates read it."""
    td = TensorDict({"observation": observation.float(), "action": action.float()}, batch_size=observation.shape[:-1])
    values = []
    for params in loss.qvalue_network_params.unbind(0):
        with params.to_module(loss.qvalue_network):
            values.append(loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values).amin(0)


def held_out_episodes(data, share: float, seed: int = 0) -> torch.Tensor:
    """True on every row of a fixed random ``share`` of the data's episodes (at least one, never all)."""
    episodes = data["episode"].unique()
    if len(episodes) < 2:
        raise ValueError(f"the data hold {len(episodes)} episode(s): holding whole episodes out needs at least 2")
    count = min(max(1, round(share * len(episodes))), len(episodes) - 1)
    chosen = episodes[torch.randperm(len(episodes), generator=torch.Generator().manual_seed(seed))[:count]]
    return torch.isin(data["episode"], chosen)


class ReturnQ(nn.Module):
    """Q(s, a): an MLP on the standardized observation and the action, its output in the return's units."""

    def __init__(self, observation: torch.Tensor, action_dim: int, target: torch.Tensor):
        super().__init__()
        self.net = MLP(in_features=observation.shape[-1] + action_dim, out_features=1, num_cells=[256, 256],
                       activation_class=nn.ReLU)
        for name, x in (("observation", observation), ("target", target)):
            self.register_buffer(f"{name}_loc", x.mean(0))
            self.register_buffer(f"{name}_scale", x.std(0).clamp_min(1e-6))

    def standardized(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        observation = (observation - self.observation_loc) / self.observation_scale
        return self.net(torch.cat([observation, action], -1)).squeeze(-1)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.target_loc + self.target_scale * self.standardized(observation, action)


def fit_return_q(data, gamma: float, horizon: int, steps: int | None = None, seed: int = 0):
    """Q fitted by least squares to the data's discounted return over the next ``horizon`` steps, on the rows
    whose return is recorded in full (:func:`known_returns`) outside the :func:`held_out_episodes`; with
    the rank correlation of its values with the returns of the held-out rows."""
    steps = RETURN_Q_STEPS if steps is None else steps
    returns, known = recorded_returns(data, gamma, horizon), known_returns(data, horizon)
    held_out = held_out_episodes(data, HELD_OUT)
    fit, check = (known & ~held_out).nonzero().flatten(), (known & held_out).nonzero().flatten()
    observation, action = data["observation"].float(), data["action"].float()
    with torch.random.fork_rng():  # the initial weights follow the seed, and the caller's stream is untouched
        torch.manual_seed(seed)
        q = ReturnQ(observation[fit], action.shape[-1], returns[fit])
    optim = torch.optim.Adam(q.parameters(), lr=3e-4)
    generator = torch.Generator().manual_seed(seed)
    target = (returns - q.target_loc) / q.target_scale
    for _ in range(steps):
        rows = fit[torch.randint(len(fit), (RETURN_Q_BATCH,), generator=generator)]
        loss = (q.standardized(observation[rows], action[rows]) - target[rows]).pow(2).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    with torch.no_grad():
        held_out_rank = row_spearman(q(observation[check], action[check]).unsqueeze(0),
                                     returns[check].unsqueeze(0)).item()
    return q.requires_grad_(False), {"rows": len(fit), "held_out_rows": len(check), "steps": steps,
                                     "held_out_rank": held_out_rank}


def local_q(run_dir, horizon: int | None = None) -> dict:
    horizon = HORIZON if horizon is None else horizon
    run = load_finished_run(run_dir, episodes=EPISODES)
    cfg = run_config(run_dir)
    gamma = float(cfg.value.gamma)
    data, _ = make_data(cfg)
    policy, observation, _, latent_actions, _ = start_candidates(run, data)  # the candidates model_selection reads
    candidate_actions = policy(own_action).actions(latent_actions)
    local, after = local_returns(run, policy, observation, candidate_actions, gamma, horizon)
    first_actions = candidate_actions[:, local]
    starts = observation[local].expand(CANDIDATES, -1, -1)
    results, _, _, loss = train_baseline("iql", data, task=run.task.name, steps=IQL_STEPS, seed=int(run.results["seed"]),
                                         eval_interval=IQL_STEPS, eval_episodes=EPISODES, eval_last_n=1,
                                         progress=False, return_policy=True, return_loss=True)
    q = min_q(loss, starts, first_actions)
    return_q, fitted = fit_return_q(data, gamma, horizon, seed=int(run.results["seed"]))
    fitted_q = return_q(starts, first_actions)
    chosen = fitted_q.argmax(0)
    return {"final_score": run.results["final_normalized_score_mean"], "horizon": horizon, "states": len(local),
            "candidates": CANDIDATES, "iql_steps": IQL_STEPS, "iql_score": results["final_normalized_score_mean"],
            "actor_return": after[0].median().item(),
            "q_rank": row_spearman(q.T, after.T).nanmedian().item(),
            "return_q": fitted | {"rank": row_spearman(fitted_q.T, after.T).nanmedian().item(),
                                  "chosen_gain": summary_of(after[chosen, torch.arange(len(local))] - after[0]),
                                  "best_gain": summary_of(after.amax(0) - after[0])}}


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    records = run_results(RESULTS) if records is None else records
    lines = ["| arm | task | seed | TELS run's score | horizon | IQL's score | IQL Q rank with the return after "
             "| return Q: held-out rank across states | return Q: rank with the return after "
             "| return gain of the return Q's first step | of the best candidate's |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (arm, task, seed), r in sorted(records.items()):
        fitted = r.get("return_q")
        cells = ("—",) * 4 if fitted is None else (
            f"{fitted['held_out_rank']:.2f}", f"{fitted['rank']:.2f}",
            *(f"{fitted[key]['median']:+.1f} ({fitted[key]['share_positive']:.0%})"
              for key in ("chosen_gain", "best_gain")))
        lines.append(f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r.get('horizon', HORIZON)} "
                     f"| {r['iql_score']:.1f} | {r['q_rank']:.2f} | {' | '.join(cells)} |")
    return "\n".join(lines)


def _summary(record: dict) -> str:
    text = f"IQL score {record['iql_score']:.1f}; Q rank with the return after {record['q_rank']:.2f}"
    if "return_q" in record:
        fitted = record["return_q"]
        text += (f"; return Q: held-out rank {fitted['held_out_rank']:.2f}, rank with the return after "
                 f"{fitted['rank']:.2f}, first-step gain {fitted['chosen_gain']['median']:+.1f} "
                 f"(best {fitted['best_gain']['median']:+.1f})")
    return text


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=local_q,
                 table=table, summary=_summary, options=HORIZON_OPTION)


if __name__ == "__main__":
    main()
