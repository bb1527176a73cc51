"""TELS offline training, Algorithm 1 of the paper, end to end.

    python recipes/tels_offline.py                      # hopper-medium-v2 10k, the default
    python recipes/tels_offline.py budget=smoke         # about 20 seconds: the default domain, small nets, few steps
    python recipes/tels_offline.py domain=paper budget=paper   # the paper as written
    python recipes/tels_offline.py run_dir=runs/x resume=true  # continue a killed run
    python recipes/tels_offline.py 'seeds=[0,1,2]'        # three seeds in one process, stacked

Stage 1 fits the TS-IDM (Eq. 7). Stage 2 encodes the dataset once with the frozen encoder and trains the latent
value (Eq. 8), then the guide policy against the updated value (Eq. 9 or 10); the policy acts through Eq. (11).
Everything a run produces lands in ``run_dir`` (``torchrl_tels.run_folder.RunFolder``); a bad config, dataset or
checkpoint stops the run before ``run_dir`` is created. With ``seeds=[...]`` every update is one ``torch.vmap``
over the seeds' stacked parameters (``torchrl_tels.seeds``), each seed built and sampled as in its own run; each
seed's outputs land in ``run_dir/seed<k>/`` and ``run_dir/results.json`` aggregates them.
"""
from __future__ import annotations

import os
import sys

# Idle OpenMP threads sleep instead of spinning, so a run sharing the machine with another
# process does not collapse (BENCHMARKS.md, "CPU threads"). OpenMP reads this once, when
# torch starts; a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from omegaconf import DictConfig, open_dict  # noqa: E402

from torchrl_tels.config import RunSpec  # noqa: E402
from torchrl_tels.envs import make_eval_envs  # noqa: E402
from torchrl_tels.errors import TelsError  # noqa: E402
from torchrl_tels.modules import save_guide_policy  # noqa: E402
from torchrl_tels.monitor import check_monitor_data, monitor_in_background, MonitorFit  # noqa: E402
from torchrl_tels.record import RunLogger, write_results, write_seeds_summary  # noqa: E402
from torchrl_tels.run import (after_training_diagnostics, check_same_stage1_length, evaluate,  # noqa: E402
                              evaluation_scalars, fit_stage2, load_pretrained_tsidm, make_data, make_stage1,
                              make_stage2, print_plan, start_run, tsidm_steps)
from torchrl_tels.seeds import SeedAxis  # noqa: E402


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    """A bad input, a bad checkpoint or a diverged loss ends the run with one ``error:`` line, exit code 2."""
    claims = []  # the run folder this process claimed, released when the run ends
    try:
        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN and not any(
                o.lstrip("+~").split("=", 1)[0] == "run_dir" for o in HydraConfig.get().overrides.task):
            with open_dict(cfg):  # hydra.sweep.dir/<job>_<overrides>: one folder per job, found again on resume
                cfg.run_dir = HydraConfig.get().runtime.output_dir
        return train(RunSpec.from_config(cfg), claims)
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    finally:
        while claims:
            claims.pop().release()


def train(spec: RunSpec, claims: list) -> dict:
    # Everything that can refuse the run is checked before run_dir is created.
    folder, run = start_run(spec)
    if run.stage == "done" and folder.is_finished:
        print(f"{folder.path} already finished; nothing to resume")
        return folder.read_results()
    stacked = spec.seeds is not None  # several seeds, each in run_dir/seed<k> as if run alone
    axis = SeedAxis(spec.seeds if stacked else [spec.seed], stacked=stacked)
    seed_folders = [folder.seed(seed) for seed in axis.seeds] if stacked else [folder]
    seed_specs = [spec.for_seed(s, f.path) for s, f in zip(axis.seeds, seed_folders)] if stacked else [spec]
    datas, tasks = zip(*(make_data(seed_spec) for seed_spec in seed_specs))
    task = tasks[0]
    if not spec.tsidm.checkpoint:
        check_same_stage1_length(spec.tsidm, datas, axis.seeds)
    for seed_spec, data in zip(seed_specs, datas):
        check_monitor_data(seed_spec, data)
    pretrained = load_pretrained_tsidm(spec, datas[0])
    print_plan(spec, len(datas[0]))
    seed_runs = run.seed_states(len(axis), stacked)
    claims.append(folder.claim(resume=spec.resume, overwrite=spec.overwrite))
    for config_spec, config_folder in [(spec, folder), *(zip(seed_specs, seed_folders) if stacked else [])]:
        config_folder.write_config(config_spec.yaml)
    logger = RunLogger(folder.path, spec.logger.exp_name, wandb_mode=spec.logger.wandb_mode,
                       project=spec.logger.project, config=spec.config, wandb_id=run.wandb_id)
    run.wandb_id = logger.wandb_id
    # The deployment monitor (monitor.pt) needs only the data: fitted beside the stages on a core the run
    # leaves free (monitor.background), waited for at the final evaluation.
    with run.time("monitor_s"):
        monitors = [MonitorFit(s, data, f, background=monitor_in_background(s) and not stacked)
                    for s, data, f in zip(seed_specs, datas, seed_folders)]

    # Algorithm 1, lines 1-4: the TS-IDM by Eq. (3)-(7).
    tsidms = make_stage1(spec, datas, axis, run, folder, seed_runs, seed_folders, logger, pretrained)
    # Line 6: encode the dataset with the frozen φ_s; build V (Eq. 8), π_g (Eq. 9/10) and the actor (Eq. 11).
    env = make_eval_envs(task.env_id, spec.eval.episodes if spec.eval.batched else 1, info_keys=task.info_keys)
    stage2 = make_stage2(spec, seed_specs, datas, tsidms, env.action_spec_unbatched, axis)

    def act(step: int) -> dict:  # Eq. (11): deterministic episodes; the last also read by the deployment monitor
        final = step == spec.policy.steps
        for monitor in monitors:
            if monitor.failed():
                monitor.get()  # a background fit that failed stops the run now, naming why
        stage2.write_back()
        with run.time("eval_s"):
            if final:
                with run.time("monitor_s"):
                    fitted = [monitor.get() for monitor in monitors]
            for k, (seed_spec, stage, seed_run) in enumerate(zip(seed_specs, stage2.stages, seed_runs)):
                with axis.use(k):
                    seed_run.evaluations.append(evaluate(
                        stage.actor, env, task, step, stage.latent_stats, eval=spec.eval, seed=seed_spec.seed,
                        compile=spec.compile, monitor=fitted[k] if final else None))
                logger.log_scalars(evaluation_scalars(seed_run.evaluations[-1], axis.prefix(k)), step)
        score = sum(seed_run.evaluations[-1]["score"] for seed_run in seed_runs) / len(seed_runs)
        return {"score": f"{score:.1f}", "eval_s": f"{run.wall['eval_s']:.0f}"}

    # Lines 7-8: V by expectile regression (Eq. 8), then the guide against the updated V (Eq. 9/10).
    start = fit_stage2(spec, stage2, run, seed_runs, folder, logger, evaluate=act)
    results = []
    for k, (seed_spec, seed_folder, data, stage, seed_run, tsidm) in enumerate(
            zip(seed_specs, seed_folders, datas, stage2.stages, seed_runs, tsidms)):
        seed_run.wall.update({key: run.wall.get(key, 0.0) for key in ("tsidm_s", "policy_s", "eval_s")})
        save_guide_policy(seed_folder.policy_path, stage.guide, latent_dim=tsidm.latent_state_dim,
                          mode=spec.guide.mode, num_cells=spec.guide.num_cells, actor_options=stage.actor_options,
                          metadata={"results": str(seed_folder.results_path)})
        # Stored with the score: a low score with a low inverse error points at the guide, a high one at the TS-IDM.
        with run.time("diagnostics_s"), axis.use(k):  # an actor acting with dropout draws from its seed's stream
            diagnostics = after_training_diagnostics(seed_spec, stage, data, task)
        results.append(write_results(seed_spec, seed_run, task, tsidm.metadata.get("beta"), diagnostics, seed_folder,
                                     tsidm_steps=tsidm_steps(spec.tsidm, len(data)),
                                     policy_steps=spec.policy.steps - start))
    summary = write_seeds_summary(folder, axis.seeds, results, run.wall) if stacked else results[0]
    run.stage, run.step = "done", spec.policy.steps
    run.save(folder.state_path)
    logger.close()
    return summary


if __name__ == "__main__":
    main()
