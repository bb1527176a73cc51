"""TELS offline training, Algorithm 1 of the paper, end to end.

    python recipes/tels_offline.py                      # hopper-medium-v2 10k, the default
    python recipes/tels_offline.py budget=smoke         # about 20 seconds, the same configuration
    python recipes/tels_offline.py domain=paper budget=paper   # the paper as written
    python recipes/tels_offline.py run_dir=runs/x resume=true  # continue a killed run

Stage 1 fits the TS-IDM (Eq. 7). Stage 2 encodes the dataset once with the
frozen encoder and trains the latent value (Eq. 8) and the guide policy
(Eq. 9 or 10); the policy acts through Eq. (11). Everything a run produces
lands in ``run_dir``: the resolved config, CSV metrics, ``tsidm.pt``,
``state.pt`` (for ``resume=true``), ``policy.pt`` (the guide; with ``tsidm.pt``
it rebuilds the actor: ``torchrl_tels.modules.load_tels_actor``), ``monitor.pt``
(the T-symmetry consistency monitor, calibrated on the training data),
``results.json`` and PNG plots. A bad config, dataset or checkpoint stops the run before
``run_dir`` is created.
"""
from __future__ import annotations

import json
import os
import sys

# Idle OpenMP threads sleep instead of spinning, so a run sharing the machine with another
# process does not collapse (BENCHMARKS.md, "CPU threads"). OpenMP reads this once, when
# torch starts; a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
import torch  # noqa: E402
import tqdm  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from torchrl_tels.config import (  # noqa: E402
    check_folder_creatable,
    check_precision_supported,
    resolve_threads,
    validate_config,
)
from torchrl_tels.envs import make_eval_envs  # noqa: E402
from torchrl_tels.errors import TelsError  # noqa: E402
from torchrl_tels.modules import save_guide_policy  # noqa: E402
from torchrl_tels.record import RunLogger, write_results  # noqa: E402
from torchrl_tels.trainer import (  # noqa: E402
    evaluate,
    load_pretrained_tsidm,
    make_data,
    make_stage1,
    make_stage2,
    RunState,
    tsidm_steps,
)


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """A bad input, a bad checkpoint or a diverged loss ends the run with one ``error:`` line, exit code 2."""
    try:
        return train(cfg)
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


def train(cfg: DictConfig) -> dict:
    # Everything that can refuse the run is checked before run_dir is created.
    validate_config(cfg)
    check_precision_supported(cfg.precision)
    torch.set_num_threads(resolve_threads(cfg.threads))
    torch.manual_seed(cfg.seed)
    run_dir = check_folder_creatable(cfg.run_dir)
    run = RunState.start(cfg, run_dir / "state.pt")
    if run.stage == "done" and (run_dir / "results.json").exists():
        print(f"{run_dir} already finished; nothing to resume")
        return json.loads((run_dir / "results.json").read_text())
    data, task = make_data(cfg)
    pretrained = load_pretrained_tsidm(cfg, data)
    if cfg.resume and (run_dir / "state.pt").exists():
        print(f"resuming {run_dir} at {run.stage} step {run.step}")

    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    logger = RunLogger(run_dir, cfg.logger.exp_name, wandb_mode=cfg.logger.wandb_mode, project=cfg.logger.project,
                       config=OmegaConf.to_container(cfg, resolve=True), wandb_id=run.wandb_id)
    run.wandb_id = logger.wandb_id

    # Algorithm 1, lines 1-4: train the TS-IDM (Eq. 3-7).
    tsidm = make_stage1(cfg, data, run, run_dir, logger, pretrained)
    # Line 6: encode the dataset with the frozen φ_s; build V (Eq. 8), π_g (Eq. 9/10), the actor (Eq. 11).
    env = make_eval_envs(task.env_id, cfg.eval.episodes if cfg.eval.batched else 1)  # the episodes as one batch
    stage2 = make_stage2(cfg, data, tsidm, env.action_spec_unbatched)
    stage2.monitor.save(run_dir / "monitor.pt")  # calibrated on the training data; recipes/export_policy.py reads it
    start = 0
    if run.resumes("policy"):
        run.restore(**stage2.modules())
        start = run.step

    with run.time("policy_s") as clock:
        progress = tqdm.tqdm(range(start, cfg.policy.steps), desc="stage 2: value + guide", file=sys.stdout,
                             initial=start, total=cfg.policy.steps, mininterval=2.0)
        for step in progress:
            # Lines 7-8: V by expectile regression, then the guide against the updated V.
            value_losses, guide_losses = stage2.update(cfg, stage2.buffer.sample(), step)
            if (step + 1) % cfg.logger.log_interval == 0:
                stage2.check_finite()
                scalars = {f"value/{k}": v.item() for k, v in value_losses.items()}
                scalars.update({f"guide/{k}": v.item() for k, v in guide_losses.items()})
                for key, value in scalars.items():
                    run.policy_history.setdefault(key, []).append((step + 1, value))
                logger.log_scalars(scalars, step + 1)
            if (step + 1) % cfg.eval.interval == 0 or step + 1 == cfg.policy.steps:
                with run.time("eval_s"):  # the final evaluation also records the consistency monitor
                    monitor = stage2.monitor if step + 1 == cfg.policy.steps else None
                    run.evaluations.append(evaluate(cfg, stage2.actor, env, task, step + 1, stage2.latent_stats,
                                                    monitor=monitor))
                logger.log_scalars({"eval/score": run.evaluations[-1]["score"],
                                    "eval/guide_step_rms": run.evaluations[-1]["guide_step_rms"]}, step + 1)
                progress.set_postfix(score=f"{run.evaluations[-1]['score']:.1f}")
            if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < cfg.policy.steps:
                stage2.check_finite()
                clock.update()
                run.step = step + 1
                run.save(run_dir / "state.pt", **{k: m.state_dict() for k, m in stage2.modules().items()})

    stage2.check_finite()
    save_guide_policy(run_dir / "policy.pt", stage2.guide, latent_dim=tsidm.latent_state_dim, mode=cfg.guide.mode,
                      num_cells=cfg.guide.num_cells, actor_options=stage2.actor_options,
                      metadata={"results": str(run_dir / "results.json")})
    results = write_results(cfg, run, task, tsidm.metadata.get("beta"), stage2.latent_stats, run_dir,
                            tsidm_steps=tsidm_steps(cfg, len(data)), policy_steps=cfg.policy.steps - start)
    run.stage, run.step = "done", cfg.policy.steps
    run.save(run_dir / "state.pt")
    logger.close()
    return results


if __name__ == "__main__":
    main()
