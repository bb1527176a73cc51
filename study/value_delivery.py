"""Is the value the guide promises delivered? V retrained as the run trained it, read from the data's states.

    python -m study.value_delivery --run-dir <run> --name <arm>-<task>-seed<k>
    python -m study.value_delivery --table

The hypothesis under test: with α = 1 the value term of Eq. (9) moves the guide's proposals to latents of
higher V than the data's next latents, but the gain is V's extrapolation off the data, not a better state:
the states the actor actually reaches (the simulator restarted from the data's states) are no better under V,
in reward, or in return over the next ``HORIZON`` steps than where the data's action, or behaviour cloning,
goes. If the reached states do gain and the actor beats BC over the horizon from the data's states, the
guide's improvement is real locally, and TELS's tie with BC over whole episodes comes from where the closed
loop drifts, not from an optimistic V.

A finished run keeps no V, so V (Eq. 8) is trained again exactly as stage 2 trained it: the run's config,
the trainer's own :func:`~torchrl_tels.trainer.make_stage2` (same seed, networks and replay buffer) and the
same number of steps; V's update never reads the guide, so with the same batches it is the run's V. The
record keeps how closely the retrained V's logged loss matches the run's (``value_loss_match``): a
stochastic guide with ℓ_Tsym draws from torch's stream at every step (``rsample``), as does an actor acting
with dropout at every evaluation, so those runs' V is retrained on other batches and the gap shows it.

Return-to-go and the data's return are known only where the data records an episode to its termination,
or far enough from the last recorded step (a timeout or the end of the file is not an end of the task).

From ``STATES`` of the run's training states (a fixed draw among those with ``HORIZON`` steps of data after
them or a recorded end), readings, each the median over states of a difference:

* ``value_rank``: rank correlation of V(φ(s)) with the data's discounted return-to-go (episodes that the
  data records to their end, or states at least ``RTG_MARGIN`` steps before the data's last step);
* ``promised``: V(π_g(z)) − V(φ(s₁ᵈ)), the proposal against the state s₁ᵈ the data's own action reaches in
  this simulator, over V's spread on the data (``replay_gap``: V(φ(s₁ᵈ)) − V(z'), against the data's recorded
  next latent z', which this simulator does not replay exactly);
* ``delivered``: V(φ(s₁)) with s₁ the state the actor's action reaches, minus V(φ(s₁ᵈ)), over the same
  spread; ``reward``: the same two steps' rewards. A step that ends the episode (a fall) reaches a state of
  value 0, as V's own targets treat it;
* ``best_random``: the largest of the same delivered gain over ``RANDOM_ACTIONS`` actions drawn uniformly
  from the action box: how much V one step can change at all, against which ``promised`` is read;
* ``horizon``: the discounted return over ``HORIZON`` steps from the data state, for the actor, for BC fitted
  to the same transitions (:func:`~study.action_error.train_bc`, ``BC_STEPS``), and the
  data's own recorded return; ``actor_over_bc``: the share of states where the actor's return is higher.

Writes ``study/results/value_delivery/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import torch
import tqdm
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.value.functional import reward2go

from benchmarks.harness import REPO
from study.action_error import train_bc
from study.heldout_selection import spearman
from study.latent_scale import run_results
from study.proposal_cap import load_finished_run, reading_main, RUN_FILES
from study.realization import set_state_from_observation, step_from_observations
from torchrl_tels.checkpoint import atomic_save
from torchrl_tels.modules.actors import GUIDE_KEY
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.trainer import autocast, make_data, make_stage2
from torchrl_tels.training import load_training_state

RESULTS = REPO / "study" / "results" / "value_delivery"
COMMAND = "python -m study.value_delivery"
STATES = 1000
HORIZON = 100
#: γ^300 < 0.05: a return-to-go cut this far from the data's last step is within 5 % of the full one.
RTG_MARGIN = 300
BC_STEPS = 5000
RANDOM_ACTIONS = 16
#: Gymnasium MuJoCo envs stepped side by side per chunk of start states (memory, not speed).
CHUNK = 250
#: Where a run's retrained V is kept, in its run folder.
VALUE_CACHE = "value_retrained.pt"


def episode_ends(data) -> torch.Tensor:
    """True on each episode's last row (the data's episodes lie in order, one after another)."""
    episode = data["episode"]
    return torch.cat([episode[1:] != episode[:-1], torch.ones(1, dtype=torch.bool)])


def terminated_episodes(data) -> torch.Tensor:
    """True on every row of an episode the data records to its termination (a timeout, or an episode the file
    or a subset cuts, is not one: its return-to-go is not known)."""
    ends, terminated = episode_ends(data), data["next", "terminated"].reshape(-1)
    out = torch.zeros(len(ends), dtype=torch.bool)
    for row in range(len(ends) - 1, -1, -1):
        out[row] = terminated[row] if ends[row] else out[row + 1]
    return out


def steps_to_end(ends: torch.Tensor) -> torch.Tensor:
    """For each row, how many rows its episode still holds after it."""
    remaining, count = torch.empty(len(ends), dtype=torch.long), 0
    for row in range(len(ends) - 1, -1, -1):
        count = 0 if ends[row] else count + 1
        remaining[row] = count
    return remaining


def recorded_returns(data, gamma: float, horizon: int | None = None) -> torch.Tensor:
    """The discounted return from each row to its episode's last row (torchrl's ``reward2go``), or over the
    next ``horizon`` steps at most."""
    reward, ends = data["next", "reward"], episode_ends(data)
    if horizon is None:
        return reward2go(reward, ends.unsqueeze(-1), gamma, time_dim=-2).squeeze(-1)
    discounts = gamma ** torch.arange(horizon, dtype=reward.dtype)
    padded = torch.cat([reward.squeeze(-1), reward.new_zeros(horizon)])
    alive = torch.cat([~ends, torch.zeros(horizon, dtype=torch.bool)])  # a row past an episode's end adds nothing
    total, weight = torch.zeros(len(reward)), torch.ones(len(reward))
    for k in range(horizon):
        total += weight * discounts[k] * padded[k:k + len(reward)]
        weight = weight * alive[k:k + len(reward)]
    return total


def discounted_returns(envs, observations: torch.Tensor, policy, horizon: int, gamma: float,
                       first_actions: torch.Tensor | None = None) -> torch.Tensor:
    """``horizon`` steps of ``policy`` (a batch of observations → actions) in ``envs``, already in the states
    ``observations`` describe, each stopped where it terminates: the discounted returns (float64). With
    ``first_actions`` (one per env), the first step takes those instead of the policy's."""
    current, total = observations.clone(), torch.zeros(len(envs), dtype=torch.float64)
    alive = torch.ones(len(envs), dtype=torch.bool)
    for k in range(horizon):
        actions = (first_actions if first_actions is not None and k == 0 else policy(current)).numpy()
        for i in alive.nonzero().flatten().tolist():
            observation, reward, terminated, _, _ = envs[i].step(actions[i])
            total[i] += gamma ** k * reward
            current[i] = torch.as_tensor(observation, dtype=current.dtype)
            alive[i] = not terminated
        if not alive.any():
            break
    return total


def rollout_returns(env_id: str, observations: torch.Tensor, policy, horizon: int, gamma: float,
                    first_actions: torch.Tensor | None = None) -> torch.Tensor:
    """From each observation's state (:func:`set_state_from_observation`), :func:`discounted_returns`."""
    returns = []
    for start in range(0, len(observations), CHUNK):
        chunk = observations[start:start + CHUNK]
        envs = [gym.make(env_id) for _ in chunk]
        try:
            for seed, (env, observation) in enumerate(zip(envs, chunk.numpy())):
                env.reset(seed=seed)
                set_state_from_observation(env, observation)
            given = None if first_actions is None else first_actions[start:start + CHUNK]
            returns.append(discounted_returns(envs, chunk, policy, horizon, gamma, given))
        finally:
            for env in envs:
                env.close()
    return torch.cat(returns).float()


def run_config(run_dir: Path):
    """The run's ``config.yaml`` over the recipe's defaults: options added to the recipe after the run was
    trained take their defaults, which are what the code did before they existed."""
    with initialize_config_dir(str(REPO / "recipes" / "config"), version_base="1.3"):
        defaults = compose("config")
    cfg = OmegaConf.merge(defaults, OmegaConf.load(RunFolder(run_dir).config_path))
    if cfg.dataset.size and cfg.dataset.subset != "trajectories":
        raise SystemExit(f"error: {run_dir} trained on a subset of single transitions (dataset.subset="
                         f"{cfg.dataset.subset}): its rows are not whole episodes, so returns cannot be read")
    with open_dict(cfg):
        cfg.device = "cpu"
    return cfg


def random_actions(action_spec, states: int) -> list[torch.Tensor]:
    """``RANDOM_ACTIONS`` batches of ``states`` actions drawn uniformly from the spec's box (a fixed draw)."""
    generator = torch.Generator().manual_seed(0)
    low, high = action_spec.space.low, action_spec.space.high
    return [low + (high - low) * torch.rand(states, len(low), generator=generator) for _ in range(RANDOM_ACTIONS)]


def retrain_value(cfg, data, tsidm, action_spec, cache: Path | None = None):
    """V trained as the run's stage 2 trained it (see the module docstring), with its logged losses.

    With ``cache``, a V retrained before for the same steps is loaded from it, and a new one is saved there
    (:data:`VALUE_CACHE` in the run folder: every reading of a run reads the same V, retrained once)."""
    stage2 = make_stage2(cfg, data, tsidm, action_spec)
    value_loss = stage2.value_loss
    params = value_loss.value_network_params
    if cache is not None and cache.exists():
        saved = torch.load(cache, weights_only=True)
        if saved["steps"] != cfg.policy.steps:
            raise SystemExit(f"error: {cache} holds V after {saved['steps']} steps, the run trained "
                             f"{cfg.policy.steps}: delete it to retrain")
        params.update_(TensorDict(saved["params"], []).unflatten_keys("."))
        losses = saved["losses"]
    else:
        losses = {}
        for step in tqdm.trange(cfg.policy.steps, desc="retraining V", mininterval=5.0):
            with autocast(cfg):
                value_losses = value_loss(stage2.buffer.sample())
            stage2.value_optim.zero_grad()
            value_losses["loss_value"].backward()
            stage2.value_optim.step()
            stage2.target_updater.step()
            if (step + 1) % cfg.logger.log_interval == 0:
                losses[step + 1] = value_losses["loss_value"].item()
        if cache is not None:
            atomic_save({"steps": cfg.policy.steps, "losses": losses,
                         "params": dict(params.data.flatten_keys(".").items())}, cache)

    @torch.no_grad()
    def value(latent: torch.Tensor) -> torch.Tensor:
        td = TensorDict({value_loss.value_network.in_keys[0]: latent}, batch_size=latent.shape[:-1])
        with params.to_module(value_loss.value_network, preserve_module_state=False):
            return value_loss.value_network(td)[value_loss.tensor_keys.value].squeeze(-1)

    return value, losses, float(cfg.value.gamma)


def known_returns(data, horizon: int) -> torch.Tensor:
    """True on the rows of ``data`` whose return over the next ``horizon`` steps the data records in full: their
    episode holds at least ``horizon`` more rows after them (one more than that return needs: the rule
    :func:`start_rows` has always drawn from, kept so that its draw and the readings made on it stay as they
    are), or ends in a termination."""
    return terminated_episodes(data) | (steps_to_end(episode_ends(data)) >= horizon)


def start_rows(data) -> torch.Tensor:
    """``STATES`` rows of ``data`` (a fixed draw) where the data's return over ``HORIZON`` steps is known."""
    eligible = known_returns(data, HORIZON).nonzero().flatten()
    return eligible[torch.randperm(len(eligible), generator=torch.Generator().manual_seed(0))[:STATES]]


def loss_match(run_dir: Path, losses: dict[int, float]) -> dict[str, float]:
    """The retrained V's logged losses against the run's own: the largest relative difference and where."""
    logged = dict(load_training_state(RunFolder(run_dir).state_path)["policy_history"]["value/loss_value"])
    shared = sorted(set(logged) & set(losses))
    gaps = [abs(losses[s] - logged[s]) / max(abs(logged[s]), 1e-12) for s in shared]
    worst = max(range(len(shared)), key=gaps.__getitem__)
    return {"steps_compared": len(shared), "max_relative_gap": gaps[worst], "at_step": shared[worst],
            "first_step_gap": gaps[0]}


def _median(x: torch.Tensor) -> float:
    return x.median().item()


def value_delivery(run_dir: Path) -> dict:
    run = load_finished_run(run_dir)
    cfg = run_config(run_dir)
    data, _ = make_data(cfg)  # the rows in the trainer's order
    value, losses, gamma = retrain_value(cfg, data, run.tsidm, run.env.action_spec_unbatched, run_dir / VALUE_CACHE)
    tsidm = run.tsidm
    with torch.no_grad():
        latent = tsidm.encode_state(data["observation"])
        v_data = value(latent)
    rtg_rows = known_returns(data, RTG_MARGIN)
    fitted = data.clone(False)  # the rewards V was fitted to
    fitted["next", "reward"] = cfg.dataset.reward_scale * data["next", "reward"] + cfg.dataset.reward_bias
    rtg = recorded_returns(fitted, gamma)
    spread = v_data.std().item()
    rows = start_rows(data)
    start = data[rows]
    observation = start["observation"]

    @torch.no_grad()
    def act(observations: torch.Tensor) -> TensorDict:  # the action, and the guide's proposal behind it
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return run.actor(TensorDict({"observation": observations}, batch_size=[len(observations)]))

    def actor(observations: torch.Tensor) -> torch.Tensor:
        return act(observations)["action"]

    bc_net = train_bc(data["observation"], data["action"], BC_STEPS, seed=int(run.results["seed"]))

    def bc(observations: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return bc_net(observations)

    env_id = run.task.env_id
    actor_return = rollout_returns(env_id, observation, actor, HORIZON, gamma)
    bc_return = rollout_returns(env_id, observation, bc, HORIZON, gamma)
    env = gym.make(env_id)
    env.reset(seed=0)
    try:
        acted = act(observation)
        first = {"actor": step_from_observations(env, observation, acted["action"]),
                 "data": step_from_observations(env, observation, start["action"])}
        random_steps = [step_from_observations(env, observation, actions)
                        for actions in random_actions(run.env.action_spec_unbatched, len(observation))]
    finally:
        env.close()

    @torch.no_grad()
    def reached_value(step) -> torch.Tensor:  # a fall ends the episode: nothing more to come
        reached, _, terminated = step
        return torch.where(terminated, 0.0, value(tsidm.encode_state(reached)))

    with torch.no_grad():
        proposal = acted[GUIDE_KEY]
        data_next_value = reached_value(first["data"])
        promised = (value(proposal) - data_next_value) / spread
        replay_gap = (data_next_value - value(tsidm.encode_state(start["next", "observation"]))) / spread
        delivered = (reached_value(first["actor"]) - data_next_value) / spread
        best_random = torch.stack([reached_value(step) - data_next_value for step in random_steps]).amax(0) / spread
    actor_reward, data_reward = first["actor"][1], first["data"][1]
    data_return = recorded_returns(data, gamma, HORIZON)[rows]
    return {
        "final_score": run.results["final_normalized_score_mean"], "gamma": gamma, "states": len(rows),
        "horizon": HORIZON, "value_loss_match": loss_match(run_dir, losses),
        "value": {"rank_with_return_to_go": spearman(v_data[rtg_rows].tolist(), rtg[rtg_rows].tolist()),
                  "return_to_go_rows": int(rtg_rows.sum()), "spread": spread,
                  "range": [v_data.min().item(), v_data.max().item()],
                  "return_to_go_range": [rtg[rtg_rows].min().item(), rtg[rtg_rows].max().item()]},
        "promised": {"median": _median(promised), "share_positive": (promised > 0).float().mean().item(),
                     "replay_gap": _median(replay_gap)},
        "delivered": {"median": _median(delivered), "share_positive": (delivered > 0).float().mean().item(),
                      "rank_with_promised": spearman(promised.tolist(), delivered.tolist())},
        "best_random": {"median": _median(best_random), "actions": RANDOM_ACTIONS,
                        "share_promised_above": (promised > best_random).float().mean().item()},
        "reward": {"median": _median(actor_reward - data_reward),
                   "share_positive": (actor_reward > data_reward).float().mean().item()},
        "horizon_return": {"actor": _median(actor_return), "bc": _median(bc_return), "data": _median(data_return),
                           "actor_minus_bc": _median(actor_return - bc_return),
                           "actor_over_bc": (actor_return > bc_return).float().mean().item(),
                           "rank_promised_with_actor_minus_bc": spearman(promised.tolist(),
                                                                         (actor_return - bc_return).tolist())},
    }


def _best_random(record: dict) -> str:
    best = record.get("best_random")  # readings from before it was recorded lack it
    return "—" if best is None else f"{best['median']:+.3f} (promised above: {best['share_promised_above']:.0%})"


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    """One row per reading (``{(arm, task, seed): record}``), in arm, task and seed order."""
    records = run_results(RESULTS) if records is None else records
    lines = ["| arm | task | seed | run's score | V rank with return-to-go | V loss: retrained against the run's "
             "| promised: V(proposal) − V(data action's next) | delivered: V(actor's next) − V(data action's next) "
             f"| best of {RANDOM_ACTIONS} random actions | reward: actor − data action | rank promised, delivered "
             f"| {HORIZON}-step return: actor, BC, data | actor above BC |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (arm, task, seed), r in sorted(records.items()):
        h = r["horizon_return"]
        lines.append(
            f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r['value']['rank_with_return_to_go']:.2f} "
            f"| {r['value_loss_match']['max_relative_gap']:.1e} "
            f"| {r['promised']['median']:+.3f} ({r['promised']['share_positive']:.0%}) "
            f"| {r['delivered']['median']:+.3f} ({r['delivered']['share_positive']:.0%}) "
            f"| {_best_random(r)} | {r['reward']['median']:+.3f} ({r['reward']['share_positive']:.0%}) "
            f"| {r['delivered']['rank_with_promised']:.2f} "
            f"| {h['actor']:.1f}, {h['bc']:.1f}, {h['data']:.1f} | {h['actor_over_bc']:.0%} |")
    return "\n".join(lines)


def _summary(record: dict) -> str:
    h = record["horizon_return"]
    return (f"promised {record['promised']['median']:+.3f}, delivered {record['delivered']['median']:+.3f}; "
            f"{HORIZON}-step return actor {h['actor']:.1f}, BC {h['bc']:.1f}, data {h['data']:.1f}")


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=value_delivery,
                 table=table, summary=_summary, required=(*RUN_FILES, RunFolder.STATE))


if __name__ == "__main__":
    main()
