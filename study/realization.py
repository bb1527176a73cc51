"""Do the states a TELS actor reaches land where its guide proposed? Rollouts of finished runs, no training.

    python -m study.realization --run-dir <run> --name <arm>-<task>-seed<k>
    python -m study.realization --table

The hypothesis under test: the value term of Eq. (9) raises V of the guide's proposals (α = 1 in the
`mujoco` preset moves it by 4-24 %), yet the return does not rise, because the chain π_g → Eq. (11) →
environment does not reach the proposed states. If so, the state reached at t + 1 lies far from
π_g(z_t) in rollouts, ``realized_error_ratio`` (:func:`torchrl_tels.diagnostics.rollout_statistics`) is
near 1 or above, and it is largest where TELS trails BC most. If it is small on every set, the actor
does go where its guide points, and TELS's shortfall lies in what the guide proposes, not in acting on it.

Each reading is ten deterministic episodes of the run as trained (seeded alike for every run), beside the
same guide's error on its own training transitions (``guide_error_ratio`` of
:func:`~torchrl_tels.diagnostics.action_chain_statistics`): how well it predicts the data's next latent,
the same quantity on states the behaviour policy visited. Writes
``study/results/realization/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import statistics
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from benchmarks.harness import REPO
from study.heldout_selection import spearman
from study.latent_scale import run_results
from study.proposal_cap import EPISODES, load_finished_run, reading_main
from torchrl_tels.diagnostics import action_chain_statistics, rollout_statistics
from torchrl_tels.envs import normalized_score, rollout_episodes
from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY

RESULTS = REPO / "study" / "results" / "realization"
COMMAND = "python -m study.realization"
ROLLOUT_KEYS = ("guide_step_rms", "realized_error_ratio", "realized_step_cosine")
#: The opening of every episode, read alone: a body that falls visits states no data holds, so the error
#: over a whole episode partly measures the fall itself. Over the opening, which all but the shortest
#: episodes survive upright, it comes before the fall.
OPENING_STEPS = 100
#: How many of the run's training states the one-step readings restart the simulator from (a fixed draw).
ONE_STEP_STATES = 1000


def set_state_from_observation(env, observation: np.ndarray) -> None:
    """Puts a Gymnasium MuJoCo locomotion env in the state its ``observation`` describes (qpos without the
    x position, then qvel, as Hopper, Walker2d and HalfCheetah observe it), at x = 0: their dynamics do not
    depend on x. Hopper and Walker2d observe velocities clipped at ±10, so such a state restarts at the clip:
    part of why replaying the data's own actions does not land exactly on its next states."""
    model = env.unwrapped.model
    if observation.shape[-1] != model.nq - 1 + model.nv:
        raise ValueError(f"an observation of size {observation.shape[-1]} is not qpos[1:] + qvel of "
                         f"{env.spec.id if env.spec else env} ({model.nq - 1} + {model.nv}): cannot set its state")
    env.unwrapped.set_state(np.concatenate([[0.0], observation[:model.nq - 1]]), observation[model.nq - 1:])


def one_step(env, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The observation one env step after each of ``observations`` under its action, the simulator
    restarted from each."""
    return step_from_observations(env, observations, actions)[0]


def step_from_observations(env, observations: torch.Tensor, actions: torch.Tensor):
    """:func:`one_step`'s observations, with each step's reward and whether it terminated the episode."""
    reached, rewards, terminated = [], [], []
    for observation, action in zip(observations.numpy(), actions.numpy()):
        set_state_from_observation(env, observation)
        step = env.step(action)
        reached.append(step[0])
        rewards.append(step[1])
        terminated.append(step[2])
    return (torch.as_tensor(np.array(reached), dtype=observations.dtype), torch.tensor(rewards),
            torch.tensor(terminated))


def _miss(reached: torch.Tensor, target: torch.Tensor, latent: torch.Tensor) -> dict[str, float]:
    """‖reached − target‖ over the step ‖target − z‖ asked for: RMS over states, and the median per state."""
    miss, asked = (reached - target).pow(2).sum(-1), (target - latent).pow(2).sum(-1)
    return {"rms": (miss.mean() / asked.mean()).sqrt().item(), "median": (miss / asked).sqrt().median().item()}


@torch.no_grad()
def one_step_readings(run, states: int = ONE_STEP_STATES) -> dict[str, dict[str, float]]:
    r"""From states of the run's own data, one simulator step each, in latent space:

    * ``data_action``: the data's action against the data's next state: how exactly this simulator
      replays the dataset (its version of MuJoCo is not the one that recorded D4RL);
    * ``inverse_action``: Eq. (11) fed the data's next latent, against that latent: the TS-IDM's part;
    * ``actor``: the actor as it acts, against its guide's proposal: are the proposals reachable?
    * ``model_data`` and ``model_actor``: the same two targets reached by the TS-IDM's own forward model,
      :math:`z + h_{fwd}(z, h_{inv}(z, \cdot))`, instead of the simulator;
    * ``rank_correlation``: over the states, how well the forward model's miss of each proposal, and
      Eq. (6) at the proposal's latent action (the guide's regularizer), rank the simulator's miss.
    """
    rows = torch.randperm(len(run.data), generator=torch.Generator().manual_seed(0))[:states]
    data = run.data[rows]
    observation = data["observation"]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        acted = run.actor(TensorDict({"observation": observation}, batch_size=[len(observation)]))
    tsidm, head = run.tsidm, run.actor[-1].module
    latent, proposal = acted[LATENT_KEY], acted[GUIDE_KEY]
    next_latent = tsidm.encode_state(data["next", "observation"])
    inverse = tsidm.decode_action(tsidm.infer_latent_action(latent, next_latent))
    if head.low is not None or head.high is not None:
        inverse = inverse.clamp(head.low, head.high)
    env = gym.make(run.task.env_id)
    env.reset(seed=0)
    try:
        reached_data, reached_inverse, reached = [tsidm.encode_state(one_step(env, observation, actions))
                                                  for actions in (data["action"], inverse, acted["action"])]
    finally:
        env.close()
    proposal_action = tsidm.infer_latent_action(latent, proposal)
    model_reached = latent + tsidm.latent_forward(latent, proposal_action)
    model_reached_data = latent + tsidm.latent_forward(latent, tsidm.infer_latent_action(latent, next_latent))
    env_miss = (reached - proposal).pow(2).sum(-1).tolist()
    return {"states": len(rows),
            "data_action": _miss(reached_data, next_latent, latent),
            "inverse_action": _miss(reached_inverse, next_latent, latent),
            "actor": _miss(reached, proposal, latent),
            "model_data": _miss(model_reached_data, next_latent, latent),
            "model_actor": _miss(model_reached, proposal, latent),
            "rank_correlation": {
                "model_miss": spearman((model_reached - proposal).pow(2).sum(-1).tolist(), env_miss),
                "tsym": spearman(tsidm.tsym_consistency(latent, proposal_action).tolist(), env_miss)}}


def realization(run_dir: Path) -> dict:
    """The run's score over ten fresh episodes, the rollout statistics (means over episodes) and the
    guide's error on its training transitions."""
    run = load_finished_run(run_dir, EPISODES)
    returns, lengths, episodes, openings = [], [], [], []
    with torch.no_grad():
        for rollout in rollout_episodes(run.actor, run.env, EPISODES, seed=run.seed):
            returns.append(rollout["next", "reward"].sum().item())
            lengths.append(rollout.shape[-1])
            episodes.append(rollout_statistics(rollout))
            openings.append(rollout_statistics(rollout[..., :OPENING_STEPS]))
    rollouts = {key: statistics.mean(e[key] for e in episodes) for key in ROLLOUT_KEYS}
    rollouts["opening_realized_error_ratio"] = statistics.mean(e["realized_error_ratio"] for e in openings)
    on_data = action_chain_statistics(run.actor, run.data)
    one_step_from_data = one_step_readings(run)
    return {"final_score": run.results["final_normalized_score_mean"],
            "score": float(normalized_score(run.task, torch.tensor(returns)).mean()), "episodes": EPISODES,
            "returns": returns, "lengths": lengths,
            "data_step_rms": run.data_step_rms, "rollouts": rollouts,
            "per_episode": episodes, "per_episode_opening": openings,
            "on_data": {k: on_data[k] for k in ("guide_step_ratio", "guide_error_ratio", "guide_step_cosine")},
            "one_step_from_data": one_step_from_data}


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    """Two tables, one row per reading (``{(arm, task, seed): record}``) in arm, task and seed order: the
    rollouts, then the one-step readings from the data's states."""
    records = run_results(RESULTS) if records is None else records
    rollout_lines = [
        "| arm | task | seed | score (these episodes) | mean episode length | data: guide error ratio "
        "| rollouts: proposed / data step | rollouts: realized error ratio "
        f"| the same over the first {OPENING_STEPS} steps | rollouts: realized step cosine |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    step_lines = [
        "| arm | task | seed | score (these episodes) | data action → data's next state "
        "| Eq. (11) on the data's next latent → that latent | actor → its guide's proposal "
        "| forward model: data's next latent | forward model: proposal "
        "| rank correlation with the simulator's miss: forward model's miss, Eq. (6) |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for (arm, task, seed), record in sorted(records.items()):
        rollouts, step = record["rollouts"], record["one_step_from_data"]
        row = f"| {arm} | {task} | {seed} | {record['score']:.1f} "
        rollout_lines.append(
            f"{row}| {statistics.mean(record['lengths']):.0f} | {record['on_data']['guide_error_ratio']:.2f} "
            f"| {rollouts['guide_step_rms'] / record['data_step_rms']:.2f} | {rollouts['realized_error_ratio']:.2f} "
            f"| {rollouts['opening_realized_error_ratio']:.2f} | {rollouts['realized_step_cosine']:.2f} |")
        ranks = step["rank_correlation"]
        step_lines.append(row + "".join(f"| {step[k]['median']:.2f} ({step[k]['rms']:.2f}) " for k in
                                        ("data_action", "inverse_action", "actor", "model_data", "model_actor"))
                          + f"| {ranks['model_miss']:.2f}, {ranks['tsym']:.2f} |")
    return "\n".join(rollout_lines + [""] + step_lines)


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=realization,
                 table=table, summary=lambda record: f"score {record['score']:.1f}; realized error ratio "
                                                      f"{record['rollouts']['realized_error_ratio']:.2f}")


if __name__ == "__main__":
    main()
