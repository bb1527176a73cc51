"""TELS offline training, Algorithm 1 of the paper, end to end.

    python recipes/tels_offline.py                      # hopper-medium-v2 10k, the default
    python recipes/tels_offline.py budget=smoke         # about 20 seconds: the default domain, small nets, few steps
    python recipes/tels_offline.py domain=paper budget=paper   # the paper as written
    python recipes/tels_offline.py run_dir=runs/x resume=true  # continue a killed run
    python recipes/tels_offline.py 'seeds=[0,1,2]'        # three seeds in one process, stacked

Stage 1 fits the TS-IDM (Eq. 7). Stage 2 encodes the dataset once with the
frozen encoder and trains the latent value (Eq. 8) and the guide policy
(Eq. 9 or 10); the policy acts through Eq. (11). Everything a run produces
lands in ``run_dir``: the resolved config, CSV metrics, ``tsidm.pt``,
``state.pt`` (for ``resume=true``), ``policy.pt`` (the guide; with ``tsidm.pt``
it rebuilds the actor: ``torchrl_tels.modules.load_tels_actor``), ``monitor.pt``
(the deployment monitor: a dynamics ensemble and the nearest data state, calibrated on
trajectories its detectors were not fitted to),
``results.json`` and PNG plots. A bad config, dataset or checkpoint stops the run before
``run_dir`` is created.

With ``seeds=[...]`` the seeds train in one process: each seed's networks are built and
its batches drawn as in its own run, and every update is one ``torch.vmap`` over the
seeds' stacked parameters (``torchrl_tels.seeds``). Each seed's outputs land in
``run_dir/seed<k>/``; ``run_dir/results.json`` aggregates them.
"""
from __future__ import annotations

import copy
import os
import sys

# Idle OpenMP threads sleep instead of spinning, so a run sharing the machine with another
# process does not collapse (BENCHMARKS.md, "CPU threads"). OpenMP reads this once, when
# torch starts; a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
import torch  # noqa: E402
import tqdm  # noqa: E402
from omegaconf import DictConfig, open_dict, OmegaConf  # noqa: E402

from torchrl_tels.config import (  # noqa: E402
    check_folder_creatable,
    check_precision_supported,
    resolve_precision,
    resolve_threads,
    validate_config,
)
from torchrl_tels.envs import make_eval_envs  # noqa: E402
from torchrl_tels.errors import TelsError  # noqa: E402
from torchrl_tels.modules import save_guide_policy, TSIDM  # noqa: E402
from torchrl_tels.monitor import check_monitor_data, make_monitor, monitor_in_background, MonitorFit  # noqa: E402
from torchrl_tels.seeds import SeedRNG  # noqa: E402
from torchrl_tels.record import RunLogger, write_results, write_seeds_summary  # noqa: E402
from torchrl_tels.run_folder import RunFolder, RunFolderClaim  # noqa: E402
from torchrl_tels.trainer import (  # noqa: E402
    after_training_diagnostics,
    check_same_stage1_length,
    evaluate,
    evaluation_scalars,
    fit_tsidm_seeds,
    load_pretrained_tsidm,
    make_data,
    make_stage1,
    make_stage2,
    print_plan,
    RunState,
    adopt_pretrained_tsidm,
    StackedStage2,
    tsidm_steps,
)


#: the run folders this process has claimed (one per run); released when ``main`` returns
CLAIMS: list[RunFolderClaim] = []


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """A bad input, a bad checkpoint or a diverged loss ends the run with one ``error:`` line, exit code 2."""
    try:
        use_sweep_job_dir(cfg)
        return train(cfg) if cfg.seeds is None else train_seeds(cfg)
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    finally:
        while CLAIMS:
            CLAIMS.pop().release()


def use_sweep_job_dir(cfg: DictConfig) -> None:
    """Under ``-m``, a job whose ``run_dir`` the user did not set runs in hydra's job folder.

    That folder is ``hydra.sweep.dir/<job number>_<the job's overrides>`` (config.yaml), unique
    per job whatever the launcher, so parallel jobs never share a folder, and the same sweep
    command (with the same ``hydra.sweep.dir``) finds the same folders again with ``resume=true``.
    """
    if not HydraConfig.initialized():
        return
    hydra_cfg = HydraConfig.get()
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return
    if any(o.lstrip("+~").split("=", 1)[0] == "run_dir" for o in hydra_cfg.overrides.task):
        return
    with open_dict(cfg):
        cfg.run_dir = hydra_cfg.runtime.output_dir


def start_run(cfg: DictConfig) -> tuple[RunFolder, RunState]:
    """Checks the config (before ``run_dir`` exists), sets threads and the global seed, loads the run's state."""
    validate_config(cfg)
    with open_dict(cfg):  # the precision the run computes in, as config.yaml and resume=true see it
        cfg.precision = resolve_precision(cfg.precision, cfg.device)
    check_precision_supported(cfg.precision, cfg.device)
    torch.set_num_threads(resolve_threads(cfg.threads))
    torch.manual_seed(cfg.seed)
    run_dir = RunFolder(check_folder_creatable(cfg.run_dir))
    run_dir.check_free(resume=cfg.resume, overwrite=cfg.overwrite)
    run = RunState.start(cfg, run_dir.state_path)
    if cfg.resume and run_dir.state_path.exists() and run.stage != "done":
        print(f"resuming {run_dir.path} at {run.stage} step {run.step}")
    return run_dir, run


def open_run_dir(cfg: DictConfig, run: RunState, run_dir: RunFolder) -> RunLogger:
    """Claims ``run_dir`` (created if need be) and writes the resolved config; the run's logger (CSV, wandb)."""
    CLAIMS.append(run_dir.claim(resume=cfg.resume, overwrite=cfg.overwrite))
    run_dir.write_config(OmegaConf.to_yaml(cfg, resolve=True))
    logger = RunLogger(run_dir.path, cfg.logger.exp_name, wandb_mode=cfg.logger.wandb_mode, project=cfg.logger.project,
                       config=OmegaConf.to_container(cfg, resolve=True), wandb_id=run.wandb_id)
    run.wandb_id = logger.wandb_id
    return logger


def finished_results(run: RunState, run_dir: RunFolder) -> dict | None:
    if run.stage == "done" and run_dir.is_finished:
        print(f"{run_dir.path} already finished; nothing to resume")
        return run_dir.read_results()
    return None


def train(cfg: DictConfig) -> dict:
    # Everything that can refuse the run is checked before run_dir is created.
    run_dir, run = start_run(cfg)
    if (done := finished_results(run, run_dir)) is not None:
        return done
    data, task = make_data(cfg)
    check_monitor_data(cfg, data)
    pretrained = load_pretrained_tsidm(cfg, data)
    print_plan(cfg, len(data))
    logger = open_run_dir(cfg, run, run_dir)
    # The deployment monitor (monitor.pt) needs only the data; recipes/export_policy.py exports it with the policy.
    # Fitted beside the stages on a core the run leaves free (monitor.background), waited for at the end.
    with run.time("monitor_s"):
        monitor = MonitorFit(cfg, data, run_dir, background=monitor_in_background(cfg))

    # Algorithm 1, lines 1-4: train the TS-IDM (Eq. 3-7).
    tsidm = make_stage1(cfg, data, run, run_dir, logger, pretrained)
    # Line 6: encode the dataset with the frozen φ_s; build V (Eq. 8), π_g (Eq. 9/10), the actor (Eq. 11).
    env = make_eval_envs(task.env_id, cfg.eval.episodes if cfg.eval.batched else 1,  # the episodes as one batch
                         info_keys=task.info_keys)
    stage2 = make_stage2(cfg, data, tsidm, env.action_spec_unbatched)
    start = 0
    if run.resumes("policy"):
        run.restore(**stage2.modules())
        start = run.step

    with run.time("policy_s"):
        progress = tqdm.tqdm(range(start, cfg.policy.steps), desc="stage 2: value + guide", file=sys.stdout,
                             initial=start, total=cfg.policy.steps, mininterval=2.0)
        for step in progress:
            # Lines 7-8: V by expectile regression, then the guide against the updated V.
            value_losses, guide_losses = stage2.update(stage2.buffer.sample(), step)
            if (step + 1) % cfg.logger.log_interval == 0:
                stage2.check_finite()
                scalars = {f"value/{k}": v.item() for k, v in value_losses.items()}
                scalars.update({f"guide/{k}": v.item() for k, v in guide_losses.items()})
                for key, value in scalars.items():
                    run.policy_history.setdefault(key, []).append((step + 1, value))
                logger.log_scalars(scalars, step + 1)
            if (step + 1) % cfg.eval.interval == 0 or step + 1 == cfg.policy.steps:
                if monitor.failed():
                    monitor.get()  # a background fit that failed stops the run now, naming why
                with run.time("eval_s"):  # the final evaluation also records the deployment monitor
                    final = step + 1 == cfg.policy.steps
                    if final:
                        with run.time("monitor_s"):
                            monitor.get()
                    run.evaluations.append(evaluate(cfg, stage2.actor, env, task, step + 1, stage2.latent_stats,
                                                    monitor=monitor.get() if final else None))
                logger.log_scalars(evaluation_scalars(run.evaluations[-1]), step + 1)
                progress.set_postfix(score=f"{run.evaluations[-1]['score']:.1f}", eval_s=f"{run.wall['eval_s']:.0f}")
            if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < cfg.policy.steps:
                stage2.check_finite()
                run.step = step + 1
                run.save(run_dir.state_path, **{k: m.state_dict() for k, m in stage2.modules().items()})

    stage2.check_finite()
    save_guide_policy(run_dir.policy_path, stage2.guide, latent_dim=tsidm.latent_state_dim, mode=cfg.guide.mode,
                      num_cells=cfg.guide.num_cells, actor_options=stage2.actor_options,
                      metadata={"results": str(run_dir.results_path)})
    # Stored with the score: a low score with a low inverse error points at the guide, a high one at the TS-IDM.
    with run.time("diagnostics_s"):
        diagnostics = after_training_diagnostics(cfg, stage2, data, task)
    results = write_results(cfg, run, task, tsidm.metadata.get("beta"), diagnostics, run_dir,
                            tsidm_steps=tsidm_steps(cfg, len(data)), policy_steps=cfg.policy.steps - start)
    run.stage, run.step = "done", cfg.policy.steps
    run.save(run_dir.state_path)
    logger.close()
    return results


def seed_config(cfg: DictConfig, seed: int, run_dir: RunFolder) -> DictConfig:
    """The config of one seed of a ``seeds`` run: what its own single-seed run would get."""
    seed_cfg = copy.deepcopy(cfg)
    with open_dict(seed_cfg):
        seed_cfg.seed, seed_cfg.seeds, seed_cfg.run_dir = seed, None, str(run_dir.seed(seed).path)
    return seed_cfg


def train_seeds(cfg: DictConfig) -> dict:
    """Algorithm 1 for every seed of ``cfg.seeds`` at once; each seed's outputs in ``run_dir/seed<k>``."""
    seeds = list(cfg.seeds)
    run_dir, run = start_run(cfg)  # the global stream, which draws inside the stacked update (dropout), too
    if (done := finished_results(run, run_dir)) is not None:
        return done
    configs = [seed_config(cfg, seed, run_dir) for seed in seeds]
    datas, task = zip(*(make_data(c) for c in configs))
    task = task[0]
    if not cfg.tsidm.checkpoint:
        check_same_stage1_length(cfg, datas, seeds)
    for c, data in zip(configs, datas):
        check_monitor_data(c, data)
    pretrained = load_pretrained_tsidm(cfg, datas[0])
    print_plan(cfg, len(datas[0]))
    seed_runs = ([RunState.from_seed_record(r) for r in run.per_seed] if run.per_seed
                 else [RunState(config={}) for _ in seeds])
    logger = open_run_dir(cfg, run, run_dir)
    seed_dirs = [run_dir.seed(seed) for seed in seeds]
    for c, seed_dir in zip(configs, seed_dirs):
        seed_dir.write_config(OmegaConf.to_yaml(c, resolve=True))
    monitors = [make_monitor(c, data, seed_dir) for c, data, seed_dir in zip(configs, datas, seed_dirs)]

    def save(**modules):
        run.per_seed = [r.seed_record() for r in seed_runs]
        run.save(run_dir.state_path, **modules)

    # Algorithm 1, lines 1-4, for all seeds at once.
    if pretrained is not None:
        tsidms = [adopt_pretrained_tsidm(cfg, pretrained, run, seed_dirs)] * len(seeds)
    elif run.stage != "tsidm":
        tsidms = [TSIDM.load(seed_dir.tsidm_path, observation_dim=data["observation"].shape[-1],
                             action_dim=data["action"].shape[-1]) for seed_dir, data in zip(seed_dirs, datas)]
    else:
        with run.time("tsidm_s"):
            trained = fit_tsidm_seeds(cfg, list(datas), seeds, run, run_dir, logger)
        tsidms = []
        for seed_dir, seed_run, (tsidm, final, history) in zip(seed_dirs, seed_runs, trained):
            seed_run.beta_results, seed_run.tsidm_history = [{"beta": float(cfg.tsidm.beta), **final}], history
            tsidm.metadata = {"beta": float(cfg.tsidm.beta), "dataset": str(cfg.dataset.name),
                              "beta_results": seed_run.beta_results}
            tsidm.save(seed_dir.tsidm_path, metadata=tsidm.metadata)
            tsidms.append(tsidm)
        run.stage, run.step = "policy", 0
        save()
    for seed_run in seed_runs:  # the seeds trained together: each ran for the whole process's time
        seed_run.wall["tsidm_s"] = run.wall.get("tsidm_s", 0.0)

    # Line 6 and the stage-2 networks, per seed on its own RNG stream; the updates are stacked.
    env = make_eval_envs(task.env_id, cfg.eval.episodes if cfg.eval.batched else 1, info_keys=task.info_keys)
    rng = SeedRNG(len(seeds))
    stages = []
    for k, (c, data, tsidm) in enumerate(zip(configs, datas, tsidms)):
        rng.start(k, c.seed)
        with rng.use(k):
            stages.append(make_stage2(c, data, tsidm, env.action_spec_unbatched))
    stage2 = StackedStage2(stages, rng, labels=[f"seed {seed}" for seed in seeds])
    torch.manual_seed(cfg.seed + 1000)  # the global stream of stage 2, the same whether or not stage 1 ran here
    start = 0
    if run.resumes("policy"):
        run.restore(**stage2.modules())
        start = run.step

    with run.time("policy_s"):
        progress = tqdm.tqdm(range(start, cfg.policy.steps), desc=f"stage 2: value + guide, {len(seeds)} seeds",
                             file=sys.stdout, initial=start, total=cfg.policy.steps, mininterval=2.0)
        for step in progress:
            value_losses, guide_losses = stage2.update(stage2.sample(), step)
            if (step + 1) % cfg.logger.log_interval == 0:
                stage2.check_finite()
                for k, (seed, seed_run) in enumerate(zip(seeds, seed_runs)):
                    scalars = {f"value/{key}": v[k].item() for key, v in value_losses.items()}
                    scalars.update({f"guide/{key}": v[k].item() for key, v in guide_losses.items()})
                    for key, value in scalars.items():
                        seed_run.policy_history.setdefault(key, []).append((step + 1, value))
                    logger.log_scalars({f"seed{seed}/{key}": v for key, v in scalars.items()}, step + 1)
            if (step + 1) % cfg.eval.interval == 0 or step + 1 == cfg.policy.steps:
                stage2.write_back()
                with run.time("eval_s"):
                    final = step + 1 == cfg.policy.steps
                    for k, (c, stage, seed_run, monitor) in enumerate(zip(configs, stages, seed_runs, monitors)):
                        with rng.use(k):
                            seed_run.evaluations.append(evaluate(c, stage.actor, env, task, step + 1,
                                                                 stage.latent_stats,
                                                                 monitor=monitor if final else None))
                        logger.log_scalars(evaluation_scalars(seed_run.evaluations[-1], f"seed{c.seed}/"), step + 1)
                progress.set_postfix(score=f"{sum(r.evaluations[-1]['score'] for r in seed_runs) / len(seeds):.1f}",
                                     eval_s=f"{run.wall['eval_s']:.0f}")
            if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < cfg.policy.steps:
                stage2.check_finite()
                run.step = step + 1
                save(**{name: m.state_dict() for name, m in stage2.modules().items()})

    stage2.check_finite()
    stage2.write_back()
    results = []
    for k, (c, seed_dir, data, stage, seed_run, tsidm) in enumerate(
            zip(configs, seed_dirs, datas, stages, seed_runs, tsidms)):
        seed_run.wall.update({key: run.wall.get(key, 0.0) for key in ("policy_s", "eval_s")})
        save_guide_policy(seed_dir.policy_path, stage.guide, latent_dim=tsidm.latent_state_dim,
                          mode=cfg.guide.mode, num_cells=cfg.guide.num_cells, actor_options=stage.actor_options,
                          metadata={"results": str(seed_dir.results_path)})
        with rng.use(k):  # an actor acting with dropout draws from its seed's own stream
            diagnostics = after_training_diagnostics(c, stage, data, task)
        results.append(write_results(c, seed_run, task, tsidm.metadata.get("beta"), diagnostics,
                                     seed_dir, tsidm_steps=tsidm_steps(c, len(data)),
                                     policy_steps=cfg.policy.steps - start))
    summary = write_seeds_summary(run_dir, seeds, results, run.wall)
    run.stage, run.step = "done", cfg.policy.steps
    save()
    logger.close()
    return summary


if __name__ == "__main__":
    main()
