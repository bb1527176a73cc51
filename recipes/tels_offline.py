"""TELS offline training, Algorithm 1 of the paper, end to end.

    python recipes/tels_offline.py                      # hopper-medium-v2 10k, paper defaults
    python recipes/tels_offline.py preset=quick         # about a minute, for smoke tests
    python recipes/tels_offline.py tsidm.beta=auto dataset.name=walker2d-medium-v2-10k
    python recipes/tels_offline.py run_dir=runs/x resume=true   # continue a killed run

Stage 1 fits the TS-IDM (Eq. 7). Stage 2 encodes the dataset once with the
frozen encoder and trains the latent value (Eq. 8) and the guide policy
(Eq. 9 or 10); the policy acts through Eq. (11). Everything a run produces
lands in ``run_dir``: the resolved config, CSV metrics, ``tsidm.pt``,
``state.pt`` (for ``resume=true``), ``policy.pt`` (the guide; with ``tsidm.pt``
it rebuilds the actor: ``torchrl_tels.modules.load_tels_actor``), ``results.json``
and PNG plots.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import SoftUpdate

from torchrl_tels.config import (
    check_precision_supported,
    check_same_run,
    check_writable_folder,
    training_config,
    validate_config,
)
from torchrl_tels.data import (
    DatasetError,
    delete_regions,
    get_task,
    load_dataset,
    make_offline_replay_buffer,
    normalized_score,
    subset_dataset,
)
from torchrl_tels.diagnostics import is_frozen, latent_statistics, rollout_statistics
from torchrl_tels.envs import make_eval_env, rollout_episodes, TSIDMEncoderTransform
from torchrl_tels.modules import make_guide_policy, make_latent_value, make_tels_actor, save_guide_policy, TSIDM
from torchrl_tels.objectives import LatentExpectileLoss, TSIDMLoss, TSymGuideLoss
from torchrl_tels.record import RunLogger
from torchrl_tels.training import (
    check_finite,
    check_finite_state,
    get_rng_state,
    is_user_error,
    load_training_state,
    plot_curves,
    save_training_state,
    set_rng_state,
    sum_losses,
    write_json,
)

TSIDM_TERMS = ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym", "ell_total", "ell_sum", "latent_rms", "latent_step_rms")
# App. B.5 picks beta by "the lowest TS-IDM training loss": "unweighted" compares the four terms'
# sum (ell_sum), "weighted" Eq. (7) itself (ell_total), which scales three terms by the candidate.
SELECTION_KEYS = {"unweighted": "final_sum", "weighted": "final_loss"}


def autocast(cfg):
    """bf16 matmuls on CPU when ``precision=bf16`` (about 2.5x faster here); fp32 otherwise."""
    return torch.autocast("cpu", dtype=torch.bfloat16, enabled=cfg.precision == "bf16")


def fit_tsidm(cfg, data, beta, candidate, state, run_dir, logger):
    """Stage 1 for one β: a fresh TS-IDM, its final losses (Eq. 7 and unweighted) and history."""
    obs_dim, act_dim = data["observation"].shape[-1], data["action"].shape[-1]
    t = cfg.tsidm
    tsidm = TSIDM(
        obs_dim,
        act_dim,
        latent_state_dim=t.latent_state_dim,
        latent_action_dim=t.latent_action_dim,
        encoder_cells=t.encoder_cells,
        decoder_cells=t.decoder_cells,
        inverse_cells=t.inverse_cells,
        action_decoder_cells=t.action_decoder_cells,
        dynamics_cells=t.dynamics_cells,
        inverse_dropout=t.inverse_dropout,
        latent_standardization=t.latent_scale == "standardized",
    )
    tsidm.fit_state_normalization(data["observation"])
    loss_module = TSIDMLoss(
        tsidm, beta=beta, ablation=t.ablation, dim_reduction=t.dim_reduction,
        relative=t.latent_scale == "relative", check_inputs=False,
    )
    optim = torch.optim.Adam(loss_module.parameters(), lr=t.lr, weight_decay=t.weight_decay, fused=True)
    buffer = make_offline_replay_buffer(data, t.batch_size)
    total_steps = t.steps or t.epochs * math.ceil(len(data) / t.batch_size)

    start, tail = 0, []  # tail: (Eq. 7, unweighted sum) over the last 10% of steps, B.5 compares final losses
    history = {key: [] for key in TSIDM_TERMS}
    if state.get("stage") == "tsidm" and state.get("candidate") == candidate and state.get("step", 0) > 0:
        loss_module.load_state_dict(state["loss"])
        optim.load_state_dict(state["optim"])
        set_rng_state(state["rng"])
        start, history, tail = state["step"], state["history"], state["tail"]

    progress = tqdm.tqdm(range(start, total_steps), desc=f"stage 1: TS-IDM beta={beta:g}", file=sys.stdout,
                         initial=start, total=total_steps, mininterval=2.0)
    for step in progress:
        with autocast(cfg):
            losses = loss_module(buffer.sample())
        check_finite(losses, f"stage 1 (TS-IDM, beta={beta:g})", step)
        optim.zero_grad()
        sum_losses(losses).backward()
        optim.step()
        if step >= int(0.9 * total_steps):  # int(): runs under 10 steps still keep their last step
            tail.append((losses["ell_total"].item(), losses["ell_sum"].item()))
        if (step + 1) % cfg.logger.log_interval == 0:
            scalars = {f"tsidm/{k}": losses[k].item() for k in TSIDM_TERMS if k in losses.keys()}
            for key, value in scalars.items():
                history[key.split("/")[1]].append((step + 1, value))
            logger.log_scalars({**scalars, "tsidm/beta": beta}, step + 1 + candidate * total_steps)
            progress.set_postfix(loss=f"{scalars['tsidm/ell_total']:.4f}")
        if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < total_steps:
            save_training_state(run_dir / "state.pt", {
                **state, "stage": "tsidm", "candidate": candidate, "step": step + 1,
                "loss": loss_module.state_dict(), "optim": optim.state_dict(),
                "rng": get_rng_state(), "history": history, "tail": tail,
            })
    check_finite_state(loss_module.state_dict(), f"stage 1 (TS-IDM, beta={beta:g}) after step {total_steps}")
    if tsidm.latent_standardization:
        tsidm.fit_latent_standardization(data["observation"])
    final = {key: sum(pair[i] for pair in tail) / len(tail) for i, key in enumerate(("final_loss", "final_sum"))}
    return tsidm.eval(), final, history


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """A bad input, a bad checkpoint or a diverged loss ends the run with one ``error:`` line, exit code 2."""
    try:
        return train(cfg)
    except Exception as err:
        if not is_user_error(err):
            raise
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


def train(cfg: DictConfig) -> dict:
    # ----------------------------------------------------------------- setup
    validate_config(cfg)
    check_precision_supported(cfg.precision)
    run_config = training_config(cfg)  # stored in every checkpoint; resume=true must match it
    run_dir = check_writable_folder(hydra.utils.to_absolute_path(cfg.run_dir))
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(cfg.seed)
    state = {}
    if cfg.resume and (run_dir / "state.pt").exists():
        state = load_training_state(run_dir / "state.pt")
        check_same_run(state.get("config"), run_config, f"checkpoint {run_dir / 'state.pt'}")
        if state["stage"] == "done" and (run_dir / "results.json").exists():
            print(f"{run_dir} already finished; nothing to resume")
            return json.loads((run_dir / "results.json").read_text())
        print(f"resuming {run_dir} at {state['stage']} step {state['step']}")
    state["config"] = run_config
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    logger = RunLogger(run_dir, cfg.logger.exp_name, wandb_mode=cfg.logger.wandb_mode,
                       project=cfg.logger.project, config=OmegaConf.to_container(cfg, resolve=True),
                       wandb_id=state.get("wandb_id"))
    state["wandb_id"] = logger.wandb_id
    wall = dict(state.get("wall", {}))

    # ------------------------------------------------------------------ data
    dataset_name = cfg.dataset.name
    source = dataset_name
    if Path(hydra.utils.to_absolute_path(str(dataset_name))).exists():
        source = hydra.utils.to_absolute_path(str(dataset_name))
    data = load_dataset(source)
    if cfg.dataset.size:
        data = subset_dataset(data, int(cfg.dataset.size), seed=cfg.seed, mode=cfg.dataset.subset)
    if cfg.dataset.delete_boxes:
        if max(cfg.dataset.delete_xy) >= data["observation"].shape[-1]:
            raise DatasetError(f"dataset.delete_xy={list(cfg.dataset.delete_xy)} names a column beyond the "
                               f"{data['observation'].shape[-1]} observation columns of {dataset_name!r}.")
        # Fig. 3's OOD test: the same seed removes the same transitions for every method.
        before = len(data)
        data = delete_regions(data, [tuple(box) for box in cfg.dataset.delete_boxes], cfg.dataset.delete_ratio,
                              seed=cfg.seed, xy_slice=list(cfg.dataset.delete_xy))
        print(f"dataset.delete_boxes: deleted {before - len(data)} of {before} transitions, {len(data)} left")
    task = get_task(cfg.dataset.task or Path(str(dataset_name)).stem)
    env = make_eval_env(task.env_id)
    env_obs_dim = env.observation_spec["observation"].shape[-1]
    if env_obs_dim != data["observation"].shape[-1] or env.action_spec.shape[-1] != data["action"].shape[-1]:
        raise DatasetError(
            f"dataset {dataset_name!r} has observation/action sizes "
            f"{data['observation'].shape[-1]}/{data['action'].shape[-1]} but env {task.env_id} has "
            f"{env_obs_dim}/{env.action_spec.shape[-1]}."
        )
    for path in ("tsidm.batch_size", "optim.batch_size"):
        if OmegaConf.select(cfg, path) > len(data):
            raise DatasetError(f"dataset {dataset_name!r} has {len(data)} transitions, fewer than "
                               f"{path}={OmegaConf.select(cfg, path)}.")

    # ------------------------------------------- stage 1: TS-IDM (Eq. 3-7)
    tsidm_path = run_dir / "tsidm.pt"
    obs_dim, act_dim = data["observation"].shape[-1], data["action"].shape[-1]
    if cfg.tsidm.checkpoint:
        tsidm = TSIDM.load(hydra.utils.to_absolute_path(cfg.tsidm.checkpoint), observation_dim=obs_dim, action_dim=act_dim)
        tsidm_history, beta_results = {}, []
        chosen_beta = tsidm.metadata.get("beta")
    elif tsidm_path.exists() and state.get("stage") == "policy":
        tsidm = TSIDM.load(tsidm_path, observation_dim=obs_dim, action_dim=act_dim)
        tsidm_history, beta_results = state["tsidm_history"], state["beta_results"]
        chosen_beta = tsidm.metadata.get("beta")
    else:
        start_time = time.perf_counter() - wall.get("tsidm_s", 0.0)
        candidates = list(cfg.tsidm.beta_candidates) if cfg.tsidm.beta == "auto" else [float(cfg.tsidm.beta)]
        beta_results = state.get("beta_results", [])
        best = None
        for candidate, beta in enumerate(candidates):
            if candidate < len(beta_results):
                continue  # finished before an interruption; its model is in best_tsidm.pt
            torch.manual_seed(cfg.seed + candidate)
            model, final, history = fit_tsidm(cfg, data, beta, candidate, state, run_dir, logger)
            beta_results.append({"beta": beta, **final})
            print(f"TS-IDM beta={beta:g}: final training loss {final['final_loss']:.5f} (Eq. 7), "
                  f"{final['final_sum']:.5f} (unweighted)")
            key = SELECTION_KEYS[cfg.tsidm.beta_selection]
            if min(r[key] for r in beta_results) == final[key]:
                best = (model, history, beta)
                model.save(run_dir / "best_tsidm.pt", metadata={"beta": beta, "history": history})
            wall["tsidm_s"] = time.perf_counter() - start_time
            state = {"stage": "tsidm", "candidate": candidate + 1, "step": 0, "beta_results": beta_results,
                     "wandb_id": logger.wandb_id, "wall": wall, "config": run_config}
            save_training_state(run_dir / "state.pt", state)
        if best is None:
            model = TSIDM.load(run_dir / "best_tsidm.pt")
            best = (model, model.metadata["history"], model.metadata["beta"])
        tsidm, tsidm_history, chosen_beta = best
        tsidm.save(tsidm_path, metadata={"beta": chosen_beta, "dataset": str(dataset_name), "beta_results": beta_results})
        print(f"stage 1 done: beta={chosen_beta:g}, TS-IDM saved to {tsidm_path}")
        wall["tsidm_s"] = time.perf_counter() - start_time
        state = {"stage": "policy", "step": 0, "wandb_id": logger.wandb_id, "wall": wall,
                 "tsidm_history": tsidm_history, "beta_results": beta_results, "config": run_config}
        save_training_state(run_dir / "state.pt", state)
    tsidm.eval()
    tsidm.requires_grad_(False)

    # ------------------------------- stage 2: latent value and guide (Eq. 8-10)
    data = data.clone()
    data["next", "reward"] = cfg.dataset.reward_scale * data["next", "reward"] + cfg.dataset.reward_bias
    # Algorithm 1, line 6: the frozen encoder maps the whole dataset once, at write time.
    buffer = make_offline_replay_buffer(data, cfg.optim.batch_size, write_transforms=[TSIDMEncoderTransform(tsidm)])
    latent_dim = tsidm.latent_state_dim
    latent_stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    data_action_std = data["action"].std(0).mean().item()
    print(f"latent scale: RMS spread {latent_stats['latent_rms']:.4g}, RMS step {latent_stats['latent_step_rms']:.4g}")
    torch.manual_seed(cfg.seed + 1000)  # the same networks whether stage 1 ran here or before a resume
    value_net = make_latent_value(latent_dim, cfg.value.num_cells)
    guide = make_guide_policy(latent_dim, cfg.guide.mode, cfg.guide.num_cells)
    value_loss = LatentExpectileLoss(value_net, expectile=cfg.value.expectile, check_inputs=False)
    value_loss.make_value_estimator(gamma=cfg.value.gamma)
    guide_loss = TSymGuideLoss(
        guide, value_net, tsidm, mode=cfg.guide.mode, alpha=cfg.guide.alpha, eta=cfg.guide.eta,
        tsym_regularizer=cfg.guide.tsym_regularizer, tsym_weight=cfg.guide.tsym_weight,
        tsym_reference=latent_stats["latent_step_rms"] ** 2 if cfg.guide.tsym_relative else None,
        max_weight=cfg.guide.max_weight,
        dim_reduction=cfg.tsidm.dim_reduction, check_inputs=False,
    )
    guide_loss.make_value_estimator(gamma=cfg.value.gamma)
    target_updater = SoftUpdate(value_loss, tau=cfg.value.target_update_rate)
    value_optim = torch.optim.Adam(value_loss.value_network_params.values(True, True), lr=cfg.value.lr, fused=True)
    guide_optim = torch.optim.Adam(guide_loss.parameters(), lr=cfg.guide.lr, fused=True)
    actor_options = {"reencode_proposal": cfg.guide.reencode_proposal, "inverse_dropout": cfg.guide.act_with_dropout}
    actor = make_tels_actor(tsidm, guide, env.action_spec, **actor_options)

    def update(batch, step):
        # Algorithm 1, line 7: V by Eq. (8); line 8: the guide against the updated V.
        with autocast(cfg):
            value_losses = value_loss(batch)
        check_finite(value_losses, "stage 2 (value)", step)
        value_optim.zero_grad()
        value_losses["loss_value"].backward()
        value_optim.step()
        with autocast(cfg):
            guide_losses = guide_loss(batch)
        check_finite(guide_losses, "stage 2 (guide)", step)
        guide_optim.zero_grad()
        sum_losses(guide_losses).backward()
        guide_optim.step()
        target_updater.step()
        return value_losses, guide_losses

    start, evaluations, policy_history = 0, [], {}
    if state.get("stage") == "policy" and state.get("step", 0) > 0:
        value_loss.load_state_dict(state["value_loss"])
        guide_loss.load_state_dict(state["guide_loss"])
        value_optim.load_state_dict(state["value_optim"])
        guide_optim.load_state_dict(state["guide_optim"])
        set_rng_state(state["rng"])
        start, evaluations, policy_history = state["step"], state["evaluations"], state["policy_history"]

    start_time = time.perf_counter() - wall.get("policy_s", 0.0)
    eval_time = wall.get("eval_s", 0.0)
    progress = tqdm.tqdm(range(start, cfg.optim.steps), desc="stage 2: value + guide", file=sys.stdout,
                         initial=start, total=cfg.optim.steps, mininterval=2.0)
    for step in progress:
        value_losses, guide_losses = update(buffer.sample(), step)
        if (step + 1) % cfg.logger.log_interval == 0:
            scalars = {f"value/{k}": v.item() for k, v in value_losses.items()}
            scalars.update({f"guide/{k}": v.item() for k, v in guide_losses.items()})
            for key, value in scalars.items():
                policy_history.setdefault(key, []).append((step + 1, value))
            logger.log_scalars(scalars, step + 1)
        if (step + 1) % cfg.eval.interval == 0 or step + 1 == cfg.optim.steps:
            eval_start = time.perf_counter()
            actor.eval()
            returns, lengths, behaviour = [], [], []
            for rollout in rollout_episodes(actor, env, cfg.eval.episodes, max_steps=cfg.eval.max_steps,
                                            seed=cfg.seed * 100_000 + (step + 1)):
                returns.append(rollout["next", "reward"].sum().item())
                lengths.append(rollout.shape[-1])
                behaviour.append(rollout_statistics(rollout))
            scores = [normalized_score(task, r) for r in returns]
            guide_step = sum(b["guide_step_rms"] for b in behaviour) / len(behaviour)
            action_std = sum(b["action_std"] for b in behaviour) / len(behaviour)
            evaluations.append({"step": step + 1, "returns": returns, "lengths": lengths, "scores": scores,
                                "score": sum(scores) / len(scores), "guide_step_rms": guide_step,
                                "action_std": action_std,
                                "frozen": is_frozen(guide_step, action_std, latent_stats["latent_step_rms"],
                                                    data_action_std)})
            logger.log_scalars({"eval/return": sum(returns) / len(returns),
                                "eval/normalized_score": evaluations[-1]["score"]}, step + 1)
            eval_time += time.perf_counter() - eval_start
            progress.set_postfix(score=f"{evaluations[-1]['score']:.1f}")
        if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < cfg.optim.steps:
            wall.update(policy_s=time.perf_counter() - start_time, eval_s=eval_time)
            save_training_state(run_dir / "state.pt", {
                "stage": "policy", "step": step + 1, "wandb_id": logger.wandb_id, "wall": wall,
                "value_loss": value_loss.state_dict(), "guide_loss": guide_loss.state_dict(),
                "value_optim": value_optim.state_dict(), "guide_optim": guide_optim.state_dict(),
                "rng": get_rng_state(), "evaluations": evaluations, "policy_history": policy_history,
                "tsidm_history": tsidm_history, "beta_results": beta_results, "config": run_config,
            })
    wall.update(policy_s=time.perf_counter() - start_time, eval_s=eval_time)
    policy_steps = cfg.optim.steps - start

    # --------------------------------------------------------------- results
    last = evaluations[-cfg.eval.last_n:]
    final = torch.tensor([e["score"] for e in last])
    tsidm_steps = cfg.tsidm.steps or cfg.tsidm.epochs * math.ceil(len(data) / cfg.tsidm.batch_size)
    results = {
        "dataset": str(dataset_name),
        "task": task.name,
        "env": task.env_id,
        "seed": cfg.seed,
        "beta": chosen_beta,
        "beta_results": beta_results,
        "final_normalized_score_mean": final.mean().item(),
        "final_normalized_score_std": final.std(unbiased=False).item(),
        "final_over_last_n_evaluations": len(last),
        "second_half_score_mean": sum(e["score"] for e in evaluations[len(evaluations) // 2:])
        / max(len(evaluations) - len(evaluations) // 2, 1),
        "evaluations": evaluations,
        "diagnostics": {
            **latent_stats,
            "data_action_std": data_action_std,
            "tsidm_history": {k: v for k, v in tsidm_history.items() if k.startswith("latent")},
            "guide_history": {k: v for k, v in policy_history.items()
                              if k in ("guide/tsym_to_state_ratio", "guide/guide_step_rms", "guide/loss_tsym",
                                       "guide/loss_guide_state", "value/value_mean")},
        },
        "wall_time_s": {"tsidm": wall.get("tsidm_s", 0.0), "policy": wall["policy_s"], "eval": wall["eval_s"]},
        "steps_per_s": {
            "tsidm": tsidm_steps * len(beta_results or [None]) / wall["tsidm_s"] if wall.get("tsidm_s") else None,
            "policy_including_eval": policy_steps / wall["policy_s"] if policy_steps else None,
            "policy_excluding_eval": policy_steps / max(wall["policy_s"] - (wall["eval_s"]), 1e-9) if policy_steps else None,
        },
    }
    save_guide_policy(run_dir / "policy.pt", guide, latent_dim=latent_dim, mode=cfg.guide.mode,
                      num_cells=cfg.guide.num_cells, actor_options=actor_options,
                      metadata={"results": str(run_dir / "results.json")})
    write_json(run_dir / "results.json", results)
    save_training_state(run_dir / "state.pt", {"stage": "done", "step": cfg.optim.steps, "wall": wall,
                                               "config": run_config})
    plot_curves({k: v for k, v in tsidm_history.items()}, run_dir / "tsidm_losses.png",
                title="TS-IDM training loss per term (unweighted)", logy=True)
    plot_curves({k: v for k, v in policy_history.items() if "loss" in k}, run_dir / "policy_losses.png",
                title="latent value and guide losses")
    plot_curves({"normalized score": [(e["step"], e["score"]) for e in evaluations]},
                run_dir / "eval_scores.png", title=f"TELS on {dataset_name}", ylabel="D4RL normalized score")
    logger.close()
    print(f"final normalized score {results['final_normalized_score_mean']:.1f} "
          f"± {results['final_normalized_score_std']:.1f} (mean of last {len(last)} evaluations); "
          f"outputs in {run_dir}")
    return results


if __name__ == "__main__":
    main()
