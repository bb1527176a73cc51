"""Run logging through TorchRL loggers: CSV always, wandb when it works."""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Mapping

from torchrl.record.loggers import CSVLogger

from torchrl_tels.run_folder import RunFolder

__all__ = ["RunLogger", "final_success_rate", "second_half_mean", "write_results", "write_seeds_summary"]

WANDB_MODES = ("online", "offline", "disabled")


class RunLogger:
    """Fans scalars out to a :class:`torchrl.record.loggers.CSVLogger` and an optional ``WandbLogger``.

    The CSV log is the record of the run. wandb is best effort: ``"online"``
    with no network or no login, or any wandb error during the run, turns
    wandb off, says so once, and the run goes on with its CSV log. wandb's
    init timeout is capped so that an unreachable server cannot stall a run.

    Args:
        log_dir: the run folder; the CSV log goes to ``log_dir/csv``.
        exp_name: experiment name.
        wandb_mode: ``"online"``, ``"offline"`` (written locally, ``wandb sync`` later) or ``"disabled"``.
        project: wandb project.
        config: the resolved run config, stored by wandb.
        wandb_id: resume this wandb run (after ``resume=true``).
    """

    def __init__(
        self,
        log_dir: str | os.PathLike,
        exp_name: str,
        *,
        wandb_mode: str = "offline",
        project: str = "torchrl_tels",
        config: Mapping | None = None,
        wandb_id: str | None = None,
        wandb_init_timeout: float = 20.0,
    ) -> None:
        if wandb_mode not in WANDB_MODES:
            raise ValueError(f"logger.wandb_mode must be one of {WANDB_MODES}, got {wandb_mode!r}.")
        self.log_dir = Path(log_dir)
        self.csv = CSVLogger(exp_name="csv", log_dir=str(self.log_dir))
        self.wandb = None
        self.wandb_id = None
        self._warned = False
        if wandb_mode == "disabled":
            return
        try:
            import wandb
            from torchrl.record.loggers import WandbLogger

            os.environ.setdefault("WANDB_SILENT", "true")
            self.wandb = WandbLogger(
                exp_name=exp_name,
                save_dir=str(self.log_dir),
                project=project,
                id=wandb_id,
                log_env_packages=False,
                mode=wandb_mode,
                config=dict(config or {}),
                settings=wandb.Settings(init_timeout=wandb_init_timeout),
            )
            self.wandb_id = getattr(self.wandb.experiment, "id", None)
        except Exception as err:  # no network, no login, bad settings: CSV carries on
            self._drop_wandb(err)

    def _drop_wandb(self, err: BaseException) -> None:
        self.wandb = None
        if not self._warned:
            self._warned = True
            warnings.warn(
                f"wandb is off for this run ({type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}); "
                f"metrics continue in {self.log_dir / 'csv'}.",
                RuntimeWarning,
                stacklevel=3,
            )

    def log_scalars(self, scalars: Mapping[str, float], step: int) -> None:
        for name, value in scalars.items():
            self.csv.log_scalar(name, float(value), step=step)
        if self.wandb is not None:
            try:
                for name, value in scalars.items():
                    self.wandb.log_scalar(name, float(value), step=step)
            except Exception as err:
                self._drop_wandb(err)

    def close(self) -> None:
        if self.wandb is not None:
            try:
                self.wandb.experiment.finish()
            except Exception as err:
                self._drop_wandb(err)


def second_half_mean(evaluations: list[Mapping]) -> float:
    """The mean score of the later half of ``evaluations`` (the middle one goes with the later half when their
    number is odd): Table 1's "last 10 of 20" for any number of evaluations, so a run's early policies never
    enter its score. NaN for no evaluations."""
    later = evaluations[len(evaluations) // 2:]
    return sum(e["score"] for e in later) / len(later) if later else float("nan")


def final_success_rate(evaluations: list[Mapping]) -> float | None:
    """The mean success rate (D4RL's criterion, e.g. Adroit) over ``evaluations``; ``None`` without one."""
    rates = [e.get("success_rate") for e in evaluations]
    return None if not rates or None in rates else sum(rates) / len(rates)


def write_results(cfg, run, task, beta, diagnostics: Mapping, run_dir, *, tsidm_steps: int, policy_steps: int) -> dict:
    """Writes ``results.json`` and the PNG plots of a finished run; returns the results.

    The score is the mean of the last ``eval.last_n`` evaluations (Table 1 reads
    the last 10 of 20); ``second_half_score_mean`` averages the later half of all
    evaluations. ``diagnostics`` holds what shows whether T-symmetry did
    anything: the latent scale, the guide's T-symmetry share and proposed step,
    and the action error split between TS-IDM and guide, as the caller measured them.
    ``monitor`` holds the deployment monitor's record of the final evaluation
    (fractions of flagged and alarmed steps, thresholds); its windowed score along
    each episode is plotted in ``monitor_scores.png`` rather than stored.
    """
    import torch

    from torchrl_tels.training import plot_curves

    folder = RunFolder(run_dir)
    run_dir = folder.path
    evaluations, wall = run.evaluations, run.wall
    last = evaluations[-cfg.eval.last_n:]
    final = torch.tensor([e["score"] for e in last])
    n_candidates = len(run.beta_results or [None])
    monitor = evaluations[-1].get("monitor") if evaluations else None
    monitor_summary = None if monitor is None else {k: v for k, v in monitor.items()
                                                   if k not in ("scores", "windows")}
    evaluations = [{**e, "monitor": monitor_summary} if "monitor" in e else e for e in evaluations]
    results = {
        "dataset": str(cfg.dataset.name),
        "task": task.name,
        "env": task.env_id,
        "score_kind": "D4RL normalized score" if task.has_reference_scores else "undiscounted return",
        "seed": cfg.seed,
        "beta": beta,
        "beta_results": run.beta_results,
        "final_normalized_score_mean": final.mean().item(),
        "final_normalized_score_std": final.std(unbiased=False).item(),
        "final_over_last_n_evaluations": len(last),
        "final_success_rate_mean": final_success_rate(last),
        "second_half_score_mean": second_half_mean(evaluations),
        "evaluations": evaluations,
        "monitor": monitor_summary,
        "diagnostics": {
            **diagnostics,
            "tsidm_history": {k: v for k, v in run.tsidm_history.items() if k.startswith("latent")},
            "guide_history": {k: v for k, v in run.policy_history.items()
                              if k in ("guide/tsym_to_state_ratio", "guide/guide_step_rms", "guide/loss_tsym",
                                       "guide/loss_guide_state", "guide/loss_reach", "guide/guide_value",
                                       "guide/advantage", "guide/clipped_weight_fraction",
                                       "guide/effective_sample_fraction", "value/state_value")},
        },
        "wall_time_s": {"tsidm": wall.get("tsidm_s", 0.0), "policy": wall["policy_s"], "eval": wall.get("eval_s", 0.0),
                        "monitor": wall.get("monitor_s"), "diagnostics": wall.get("diagnostics_s")},
        "steps_per_s": {
            "tsidm": tsidm_steps * n_candidates / wall["tsidm_s"] if wall.get("tsidm_s") else None,
            "policy_including_eval": policy_steps / wall["policy_s"] if policy_steps else None,
            "policy_excluding_eval": policy_steps / max(wall["policy_s"] - wall.get("eval_s", 0.0), 1e-9)
            if policy_steps else None,
        },
    }
    folder.write_results(results)
    plot_curves(run.tsidm_history, run_dir / "tsidm_losses.png",
                title="TS-IDM training loss per term (unweighted) and latent scale", logy=True)
    plot_curves({k: v for k, v in run.policy_history.items() if "loss" in k or "ratio" in k},
                run_dir / "policy_losses.png", title="latent value and guide losses; T-symmetry share", logy=True)
    plot_curves({"score": [(e["step"], e["score"]) for e in evaluations]}, run_dir / "eval_scores.png",
                title=f"TELS on {cfg.dataset.name}: each evaluation's mean, its episodes and their middle half",
                ylabel=results["score_kind"],
                spread={"score": [(e["step"], e.get("scores") or []) for e in evaluations]})
    if monitor is not None and monitor.get("windows"):
        longest = max(len(window) for window in monitor["windows"])
        series = {f"episode {i}": list(enumerate(window, 1)) for i, window in enumerate(monitor["windows"])}
        threshold = monitor["window_threshold"]
        series[f"alarm threshold (q={monitor['window_quantile']:g})"] = [(1, threshold), (longest, threshold)]
        plot_curves(series, run_dir / "monitor_scores.png", xlabel="env step",
                    ylabel=f"mean {monitor['score']} ood_score over {monitor['window']} steps",
                    title=f"deployment monitor, final evaluation: {monitor['ood_fraction']:.1%} of steps flagged, "
                          f"{monitor['alarm_fraction']:.1%} alarmed")
    print(f"final score {results['final_normalized_score_mean']:.1f} ± {results['final_normalized_score_std']:.1f} "
          f"(mean of last {len(last)} evaluations; {results['score_kind']}); outputs in {run_dir}")
    return results


def write_seeds_summary(run_dir, seeds, results: list, wall: Mapping) -> dict:
    """``run_dir/results.json`` of a ``seeds`` run: each seed's final score, their mean and (population) std.

    ``wall_time_s`` is the whole process's (all seeds trained together), and
    ``seed_runs_per_hour`` the seeds it finished per hour of it.
    """
    import numpy as np

    folder = RunFolder(run_dir)
    scores = np.array([r["final_normalized_score_mean"] for r in results])
    total = wall.get("tsidm_s", 0.0) + wall["policy_s"]
    summary = {
        "seeds": list(seeds),
        "score_kind": results[0]["score_kind"],
        "dataset": results[0]["dataset"],
        "final_scores": {str(seed): float(score) for seed, score in zip(seeds, scores)},
        "final_score_mean": float(scores.mean()),
        "final_score_std": float(scores.std()),
        "per_seed_results": [str(folder.seed(seed).results_path) for seed in seeds],
        "wall_time_s": {"tsidm": wall.get("tsidm_s", 0.0), "policy": wall["policy_s"], "eval": wall.get("eval_s", 0.0),
                        "total": total},
        "seed_runs_per_hour": len(seeds) * 3600.0 / total if total else None,
    }
    folder.write_results(summary)
    print(f"{len(seeds)} seeds: final score {summary['final_score_mean']:.1f} ± {summary['final_score_std']:.1f} "
          f"over seeds; per seed in {run_dir}/seed<k>/")
    return summary
