"""Can the TS-IDM's own forward model choose, among latent actions near the actor's, one that reaches more value?

    python -m study.model_selection --run-dir <run> --name <arm>-<task>-seed<k>
    python -m study.model_selection --table

``value_delivery`` found that Eq. (9) reads V at a proposed latent that no action reaches: the promised gain
is not delivered. The hypothesis here: V read where the TS-IDM's forward model says an action goes delivers.
Among ``CANDIDATES`` latent actions z_aᵏ = z_a⁰ + σ·εᵏ around the actor's own, z_a⁰ = h_inv(z, π_g(z)) of
Eq. (11) (k = 0; εᵏ standard normal; σ = ``SCALE`` × the per-dimension std of the data's latent actions
h_inv(φ(s), φ(s'))), act ψ_a(z_aᵏ) for the k of largest V(z + h_fwd(z, z_aᵏ)), the next latent Eq. (6)'s
forward model predicts. V is the run's own (``value_delivery.retrain_value``, cached in the run folder).

The hypothesis is refuted if any of these fails:

* ``model_rank``: within a state, the rank correlation over the candidates of V at the predicted next latent
  with V at the state the simulator reaches from that state with that candidate's action (0 where it falls),
  the median over ``value_delivery``'s start states. Near 0, the forward model cannot rank the candidates;
  ``tsym_rank`` is the same for minus Eq. (6)'s consistency error, T-symmetry's own flag of a bad transition;
* ``chosen``: the reached value of the chosen candidate minus the actor's own (k = 0), over V's spread on the
  data; against ``best`` (the largest over the candidates: what a perfect ranking would gain) and ``other``
  (a fixed candidate k = 1: what perturbing alone does), and the model's own promise ``predicted``;
* ``local``: does V order one step's alternatives by the return that follows them? From the first
  ``LOCAL_STATES`` start states, each candidate's action first, then the actor for ``horizon`` - 1 steps: within a
  state, the rank correlation over the candidates of this discounted return with V at the state the first step
  reached (``value_rank``), with V at the predicted next latent (``model_rank``), with the first step's reward
  (``reward_rank``) and with the one-step target r + γ·V(s') (``reward_and_value_rank``), and the return of the
  chosen candidate's first step minus the actor's own (``chosen_gain``). V ranks the data's states by their
  return-to-go across episodes (``value_delivery``); near 0 here, it cannot tell one step's alternatives apart,
  and no choice by V, of a proposal or of an action, can deliver. ``return_spread``: the std of these
  returns over the candidates (scaled as V's rewards) over V's spread on the data, the precision a local
  choice needs. How far the return that follows is predictable at all: ``repeat_rank``, the same rank
  correlation of the returns with those after first actions nudged by ``NUDGE`` (in the action box's
  half-widths, a fixed random sign per dimension), the ceiling of any ranking where small differences in the
  first step grow into large ones later;
* ``horizon_return``: the discounted return over ``horizon`` steps from the start states, choosing at every step,
  against the actor and against choosing at random among the same candidates;
* ``episodes``: the normalized score over ``EPISODES`` whole evaluation episodes, seeded alike for the
  actor, the chosen candidate and a random one.

``horizon`` is ``HORIZON`` unless ``--horizon`` says otherwise: at γ = 0.99 a 100-step return leaves out
what happens later, a fall after step 100 included, which ``oracle_choice`` finds decides which candidate is
better; 300 steps leave out about 5 % of the discounted return.

Writes ``study/results/model_selection/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import statistics
from typing import Callable, NamedTuple

import gymnasium as gym
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from benchmarks.harness import REPO
from study.latent_scale import run_results
from study.proposal_cap import EPISODES, FinishedRun, load_finished_run, reading_main, RUN_FILES
from study.realization import step_from_observations
from study.value_delivery import (HORIZON, retrain_value, rollout_returns, run_config,
                                  start_rows, VALUE_CACHE)
from torchrl_tels.envs import evaluate_policy, normalized_score
from torchrl_tels.modules import TSIDM
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.trainer import make_data

RESULTS = REPO / "study" / "results" / "model_selection"
COMMAND = "python -m study.model_selection"
CANDIDATES = 16
#: ``reading_main``'s option for the readings of these candidates' returns
HORIZON_OPTION = {"horizon": {"type": int, "help": f"steps of every return read (default {HORIZON})"}}
SCALE = 0.5
LOCAL_STATES = 200
NUDGE = 0.01


def row_spearman(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per row of two ``(rows, k)`` tensors, the rank correlation across the k columns, tied values sharing
    their mean rank (candidates that all fall reach the same value, 0); NaN where a row is constant."""
    def centred_ranks(t):
        below = (t.unsqueeze(-1) > t.unsqueeze(-2)).sum(-1)
        tied = (t.unsqueeze(-1) == t.unsqueeze(-2)).sum(-1)
        ranks = below.double() + (tied.double() - 1) / 2
        return ranks - ranks.mean(-1, keepdim=True)

    rx, ry = centred_ranks(x), centred_ranks(y)
    return (rx * ry).sum(-1) / (rx.norm(dim=-1) * ry.norm(dim=-1))


class LatentActionChoice(nn.Module):
    """Observation → action: the actor's latent action of Eq. (11) and ``CANDIDATES - 1`` Gaussian perturbations
    of it, decoded by ψ_a and clipped like the actor's; ``choose`` picks one per state from the candidates'
    ``(latent, latent actions, predicted next latents)`` (:func:`own_action`: the actor's own)."""

    def __init__(self, tsidm: TSIDM, guide: nn.Module, head: nn.Module, sigma: torch.Tensor, choose, seed: int = 0):
        super().__init__()
        self.tsidm, self.guide, self.head, self.choose = tsidm, guide, head, choose
        self.register_buffer("sigma", sigma)
        self.generator = torch.Generator().manual_seed(seed)

    @torch.no_grad()
    def own_latent_action(self, latent: torch.Tensor) -> torch.Tensor:
        """The actor's latent action h_inv(z, π_g(z)) of Eq. (11)."""
        return self.head.latent_action(latent, self.guide(latent))

    @torch.no_grad()
    def own_actions(self, observation: torch.Tensor) -> torch.Tensor:
        """The actor's actions, without drawing candidates."""
        return self.actions(self.own_latent_action(self.tsidm.encode_state(observation)))

    @torch.no_grad()
    def candidates(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(z, z_a, predicted next latents)``, candidates first: ``(CANDIDATES, states, ·)``."""
        tsidm = self.tsidm
        latent = tsidm.encode_state(observation)
        own = self.own_latent_action(latent)
        noise = torch.randn((CANDIDATES - 1, *own.shape), generator=self.generator)
        latent_actions = torch.cat([own.unsqueeze(0), own + self.sigma * noise.to(own)])
        latents = latent.expand(CANDIDATES, *latent.shape)
        return latent, latent_actions, latents + tsidm.latent_forward(latents, latent_actions)

    @torch.no_grad()
    def actions(self, latent_actions: torch.Tensor) -> torch.Tensor:
        return self.head.action(latent_actions)

    @torch.no_grad()
    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if observation.dim() == 1:  # one env's observation, unbatched
            return self(observation.unsqueeze(0)).squeeze(0)
        latent, latent_actions, predicted = self.candidates(observation)
        pick = self.choose(latent, latent_actions, predicted)
        return self.actions(latent_actions[pick, torch.arange(len(pick))])


def own_action(latent, latent_actions, predicted):
    """The actor's own latent action (k = 0): the run's actor, acting through this module."""
    return torch.zeros(latent.shape[0], dtype=torch.long)


def by_value(value):
    """Choose the candidate of largest V at its predicted next latent."""
    return lambda latent, latent_actions, predicted: value(predicted).argmax(0)


def at_random(seed: int = 1):
    """Choose a candidate uniformly at random (a fixed stream)."""
    generator = torch.Generator().manual_seed(seed)
    return lambda latent, latent_actions, predicted: torch.randint(CANDIDATES, (latent.shape[0],), generator=generator)


def summary_of(x: torch.Tensor) -> dict:
    """Median, mean and the share above 0 of ``x``."""
    return {"median": x.median().item(), "mean": x.mean().item(), "share_positive": (x > 0).float().mean().item()}


def candidate_policies(run, data):
    """``choose`` → the run's :class:`LatentActionChoice`, with σ from the latent actions of ``data`` (its
    training transitions); every policy it makes draws the same candidates for the same observations."""
    tsidm, guide, head = run.tsidm, run.actor[1].module, run.actor[-1].module
    if head.inverse_dropout:
        raise SystemExit("error: the run acts with h_inv's dropout on: its latent action is not one number")
    with torch.no_grad():
        latent = tsidm.encode_state(data["observation"])
        sigma = SCALE * tsidm.infer_latent_action(latent, tsidm.encode_state(data["next", "observation"])).std(0)
    return lambda choose: LatentActionChoice(tsidm, guide, head, sigma, choose)


def returns_after(run, policy, observation: torch.Tensor, first_actions: torch.Tensor, gamma: float,
                  horizon: int | None = None) -> torch.Tensor:
    """``(candidates, states)``: the discounted return over ``horizon`` steps (``HORIZON``) from each state, the
    first step taking each candidate's action of ``first_actions`` ``(candidates, states, ·)``, then ``policy``."""
    horizon = HORIZON if horizon is None else horizon
    return rollout_returns(run.task.env_id, observation.repeat(len(first_actions), 1), policy, horizon, gamma,
                           first_actions=first_actions.flatten(0, 1)).reshape(len(first_actions), len(observation))


def start_candidates(run, data):
    """The run's candidate policies (:func:`candidate_policies`), the observations of ``value_delivery``'s start
    states and their candidates ``(z, z_a, predicted next latents)``."""
    policy = candidate_policies(run, data)
    observation = data[start_rows(data)]["observation"]
    return policy, observation, *policy(own_action).candidates(observation)


class CandidateReading(NamedTuple):
    """What a reading of one finished run's candidates starts from: the run and its config, its training rows
    in the trainer's order, its V (:func:`value_delivery.retrain_value`, cached in the run folder) with γ, and
    :func:`start_candidates`."""
    run: FinishedRun
    cfg: DictConfig
    data: TensorDictBase
    value: Callable[[torch.Tensor], torch.Tensor]
    gamma: float
    policy: Callable[..., LatentActionChoice]
    observation: torch.Tensor
    latent: torch.Tensor
    latent_actions: torch.Tensor
    predicted: torch.Tensor


def read_candidates(run_dir) -> CandidateReading:
    run = load_finished_run(run_dir, episodes=EPISODES)
    cfg = run_config(run_dir)
    data, _ = make_data(cfg)
    value, _, gamma = retrain_value(cfg, data, run.tsidm, run.env.action_spec_unbatched, run_dir / VALUE_CACHE)
    return CandidateReading(run, cfg, data, value, gamma, *start_candidates(run, data))


def local_returns(run, policy, observation: torch.Tensor, candidate_actions: torch.Tensor, gamma: float,
                  horizon: int | None = None):
    """From the first ``LOCAL_STATES`` start states: their indices and :func:`returns_after` with the candidates'
    actions ``candidate_actions`` ``(candidates, states, ·)`` first, then the actor."""
    local = torch.arange(min(LOCAL_STATES, len(observation)))
    return local, returns_after(run, policy(own_action), observation[local], candidate_actions[:, local], gamma,
                                horizon)


def model_selection(run_dir, horizon: int | None = None) -> dict:
    horizon = HORIZON if horizon is None else horizon
    run, cfg, data, value, gamma, policy, observation, latent, latent_actions, predicted = read_candidates(run_dir)
    tsidm = run.tsidm
    chooser = policy(own_action)
    head, candidate_actions = chooser.head, chooser.actions(latent_actions)  # (candidates, states, ·)
    with torch.no_grad():
        spread = value(tsidm.encode_state(data["observation"])).std().item()
        predicted_value = value(predicted)
        consistency = tsidm.tsym_consistency(latent.expand(CANDIDATES, -1, -1), latent_actions,
                                             cfg.tsidm.dim_reduction)
    env = gym.make(run.task.env_id)
    env.reset(seed=0)
    try:
        reached, rewards = [], []  # V at the state each candidate's action reaches (0 where it falls), reward
        for k in range(CANDIDATES):
            next_observation, reward, terminated = step_from_observations(env, observation, candidate_actions[k])
            with torch.no_grad():
                reached.append(torch.where(terminated, 0.0, value(tsidm.encode_state(next_observation))))
            rewards.append(cfg.dataset.reward_scale * reward.float() + cfg.dataset.reward_bias)  # V's units
    finally:
        env.close()
    reached, rewards = torch.stack(reached), torch.stack(rewards)  # (candidates, states)
    chosen = predicted_value.argmax(0)
    states = torch.arange(len(observation))
    gain = lambda x: (x - reached[0]) / spread
    model_rank = row_spearman(predicted_value.T, reached.T)
    tsym_rank = row_spearman(-consistency.T, reached.T)

    local, after = local_returns(run, policy, observation, candidate_actions, gamma, horizon)
    local_gain = after[chosen[local], local] - after[0]
    first_actions = candidate_actions[:, local]
    half_width = (head.high - head.low) / 2
    signs = torch.randint(2, first_actions.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    nudged = (first_actions + NUDGE * half_width * signs).clamp(head.low, head.high)
    after_nudged = returns_after(run, policy(own_action), observation[local], nudged, gamma, horizon)

    choices = {"actor": own_action, "chosen": by_value(value), "random": at_random()}
    returns_over_horizon = {name: rollout_returns(run.task.env_id, observation, policy(choose), horizon, gamma)
                            for name, choose in choices.items()}
    episodes = {}
    for name, choose in choices.items():
        module = TensorDictModule(policy(choose), in_keys=["observation"], out_keys=["action"])
        returns = evaluate_policy(module, run.env, EPISODES, seed=run.seed)
        episodes[name] = float(normalized_score(run.task, torch.tensor(returns)).mean())
    return {
        "final_score": run.results["final_normalized_score_mean"], "gamma": gamma, "horizon": horizon,
        "states": len(observation),
        "candidates": CANDIDATES, "scale": SCALE, "value_spread": spread,
        "model_rank": {"median": model_rank.nanmedian().item(), "rows": int(model_rank.isfinite().sum())},
        "tsym_rank": {"median": tsym_rank.nanmedian().item(), "rows": int(tsym_rank.isfinite().sum())},
        "predicted": summary_of((predicted_value[chosen, states] - predicted_value[0]) / spread),
        "chosen": summary_of(gain(reached[chosen, states])),
        "best": summary_of(gain(reached.amax(0))),
        "other": summary_of(gain(reached[1])),
        "local": {"states": len(local), "value_rank": row_spearman(reached[:, local].T, after.T).nanmedian().item(),
                  "model_rank": row_spearman(predicted_value[:, local].T, after.T).nanmedian().item(),
                  "reward_rank": row_spearman(rewards[:, local].T, after.T).nanmedian().item(),
                  "reward_and_value_rank": row_spearman((rewards + gamma * reached)[:, local].T,
                                                        after.T).nanmedian().item(),
                  "repeat_rank": row_spearman(after_nudged.T, after.T).nanmedian().item(), "nudge": NUDGE,
                  "actor_return": after[0].median().item(), "chosen_gain": summary_of(local_gain),
                  # how much the alternatives' returns differ, in V's units, against V's spread over the data
                  "return_spread": (cfg.dataset.reward_scale * after.std(0) / spread).median().item()},
        "horizon_return": {name: returns.median().item() for name, returns in returns_over_horizon.items()}
        | {"chosen_over_actor": (returns_over_horizon["chosen"] > returns_over_horizon["actor"]).float().mean().item(),
           "random_over_actor": (returns_over_horizon["random"] > returns_over_horizon["actor"]).float().mean().item()},
        "episodes": {"count": EPISODES, "scores": episodes},
    }


def _cell(summary: dict) -> str:
    return f"{summary['median']:+.3f} ({summary['share_positive']:.0%})"


def _local_ranks(local: dict | None) -> str:
    if local is None:
        return "—"
    ranks = [local[key] for key in ("value_rank", "model_rank", "reward_rank", "reward_and_value_rank")
             if key in local]
    ceiling = f"; {local['repeat_rank']:.2f}" if "repeat_rank" in local else ""
    return ", ".join(f"{rank:.2f}" for rank in ranks) + ceiling


def _return_spread(local: dict | None) -> str:
    return "—" if local is None or "return_spread" not in local else f"{local['return_spread']:.3f}"


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    """One row per reading (``{(arm, task, seed): record}``), in arm, task and seed order."""
    records = run_results(RESULTS) if records is None else records
    lines = ["| arm | task | seed | run's score | model rank | T-symmetry rank | predicted gain of the chosen "
             "| reached gain: chosen | best candidate | other candidate "
             "| local: rank with the return after of V, model, reward, r + γV; nudged repeat "
             "| local: return spread over V's spread | local: return gain of the chosen first step "
             "| horizon | return over the horizon: actor, chosen, random | chosen above actor "
             f"| {EPISODES} episodes: actor, chosen, random |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (arm, task, seed), r in sorted(records.items()):
        h, e, local = r["horizon_return"], r["episodes"]["scores"], r.get("local")
        lines.append(
            f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r['model_rank']['median']:.2f} "
            f"| {r['tsym_rank']['median']:.2f} | {_cell(r['predicted'])} | {_cell(r['chosen'])} "
            f"| {_cell(r['best'])} | {_cell(r['other'])} | {_local_ranks(local)} | {_return_spread(local)} "
            f"| {'—' if local is None else _cell(local['chosen_gain'])} | {r.get('horizon', HORIZON)} "
            f"| {h['actor']:.1f}, {h['chosen']:.1f}, {h['random']:.1f} "
            f"| {h['chosen_over_actor']:.0%} | {e['actor']:.1f}, {e['chosen']:.1f}, {e['random']:.1f} |")
    return "\n".join(lines + ["", *episode_changes(records)])


def episode_changes(records: dict[tuple[str, str, int], dict]) -> list[str]:
    """Per arm and task, the paired change of the episodes' score from the actor's, for the chosen and the
    random candidate: the mean over seeds and how many seeds are up."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for (arm, task, _), record in sorted(records.items()):
        groups.setdefault((arm, task), []).append(record["episodes"]["scores"])
    lines = []
    for (arm, task), scores in groups.items():
        cells = []
        for name in ("chosen", "random"):
            changes = [s[name] - s["actor"] for s in scores]
            cells.append(f"{name} {statistics.mean(changes):+.1f} ({sum(c > 0 for c in changes)} of {len(changes)} up)")
        lines.append(f"- {arm}, {task}, {EPISODES} episodes against the actor's: {'; '.join(cells)}.")
    return lines


def _summary(record: dict) -> str:
    e = record["episodes"]["scores"]
    return (f"model rank {record['model_rank']['median']:.2f}, reached gain chosen "
            f"{record['chosen']['median']:+.3f} (best {record['best']['median']:+.3f}); episodes actor "
            f"{e['actor']:.1f}, chosen {e['chosen']:.1f}, random {e['random']:.1f}")


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=model_selection,
                 table=table, summary=_summary, required=(*RUN_FILES, RunFolder.STATE), options=HORIZON_OPTION)


if __name__ == "__main__":
    main()
