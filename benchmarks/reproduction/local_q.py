"""Does IQL's Q order one step's alternatives by the return that follows, where TELS's V does not?

    python -m benchmarks.reproduction.local_q --run-dir <run> --name <arm>-<task>-seed<k>
    python -m benchmarks.reproduction.local_q --table

``model_selection`` reads, from a TELS run's start states, how well V at the state each of ``CANDIDATES``
first actions reaches ranks the discounted return that follows (each candidate's action, then the actor).
Low there, the question is whether value learning on these few transitions fails at this in general, or
TELS's V (a state value in the TS-IDM's latent space) in particular. This reading trains IQL
(:func:`benchmarks.baselines.train_baseline`, torchrl's ``IQLLoss`` and its offline config) on the run's own
training transitions for ``IQL_STEPS`` steps and reads, on the same states, candidates and returns, the
rank correlation of min(Q₁, Q₂)(s, a) with the return after (``q_rank``). IQL's own score, from its final
evaluation, says what this Q does as a policy.

Writes ``benchmarks/reproduction/results/local_q/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import torch
from tensordict import TensorDict

from benchmarks.baselines import train_baseline
from benchmarks.harness import REPO
from benchmarks.reproduction.latent_scale import run_results
from benchmarks.reproduction.model_selection import (CANDIDATES, local_returns, own_action, row_spearman,
                                                     start_candidates)
from benchmarks.reproduction.proposal_cap import EPISODES, load_finished_run, reading_main
from benchmarks.reproduction.value_delivery import run_config
from torchrl_tels.trainer import make_data

RESULTS = REPO / "benchmarks" / "reproduction" / "results" / "local_q"
COMMAND = "python -m benchmarks.reproduction.local_q"
IQL_STEPS = 20_000


@torch.no_grad()
def min_q(loss, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """IQL's min(Q₁, Q₂)(s, a), as its policy and value updates read it."""
    td = TensorDict({"observation": observation.float(), "action": action.float()}, batch_size=observation.shape[:-1])
    values = []
    for params in loss.qvalue_network_params.unbind(0):
        with params.to_module(loss.qvalue_network):
            values.append(loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values).amin(0)


def local_q(run_dir) -> dict:
    run = load_finished_run(run_dir, episodes=EPISODES)
    cfg = run_config(run_dir)
    data, _ = make_data(cfg)
    policy, observation, _, latent_actions, _ = start_candidates(run, data)  # the candidates model_selection reads
    candidate_actions = policy(own_action).actions(latent_actions)
    local, after = local_returns(run, policy, observation, candidate_actions, float(cfg.value.gamma))
    first_actions = candidate_actions[:, local]
    results, _, _, loss = train_baseline("iql", data, task=run.task.name, steps=IQL_STEPS, seed=int(run.results["seed"]),
                                         eval_interval=IQL_STEPS, eval_episodes=EPISODES, eval_last_n=1,
                                         progress=False, return_policy=True, return_loss=True)
    q = min_q(loss, observation[local].expand(CANDIDATES, -1, -1), first_actions)
    return {"final_score": run.results["final_normalized_score_mean"], "states": len(local),
            "candidates": CANDIDATES, "iql_steps": IQL_STEPS, "iql_score": results["final_normalized_score_mean"],
            "actor_return": after[0].median().item(),
            "q_rank": row_spearman(q.T, after.T).nanmedian().item()}


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    records = run_results(RESULTS) if records is None else records
    lines = ["| arm | task | seed | TELS run's score | IQL's score | IQL Q rank with the return after |",
             "|---|---|---|---|---|---|"]
    for (arm, task, seed), r in sorted(records.items()):
        lines.append(f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r['iql_score']:.1f} | {r['q_rank']:.2f} |")
    return "\n".join(lines)


def _summary(record: dict) -> str:
    return f"IQL score {record['iql_score']:.1f}; Q rank with the return after {record['q_rank']:.2f}"


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=local_q,
                 table=table, summary=_summary)


if __name__ == "__main__":
    main()
