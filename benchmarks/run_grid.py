"""TELS against TorchRL's offline baselines on the D4RL-10k locomotion sets: run, collect, tabulate.

One command trains and evaluates ONE (method, task, seed) and writes
``<results-dir>/<method>/<task>/seed<k>.json`` (temp file + rename); a result
that exists is skipped unless ``--force``, so a grid can be spread over job
arrays, wandb sweep agents and several machines. Run from the repository root::

    python -m benchmarks.run_grid --method iql --task hopper-medium-v2-10k --seed 0 --threads 2
    python -m benchmarks.run_grid --method=tels --task=walker2d-medium-v2-10k --seed=1   # wandb's ${args} form
    python -m benchmarks.run_grid --grid --seed 0 1 2            # every missing combination, one after another
    python -m benchmarks.run_grid --list --seed 0 1 2 > jobs.txt  # one command per missing run (job arrays)
    python -m benchmarks.run_grid --table                        # TABLE.md and PNGs, beside long20k and long50k
    python -m benchmarks.run_grid --table --results-dir DIR --longer DIR2       # another grid beside a longer one
    python -m benchmarks.run_grid --method iql ... --set reward_scale=return_range --results-dir DIR  # a baseline option
    python -m benchmarks.run_grid --grid --method tels ... --work-dir NEW --tsidm-from OLD  # stage 2 again on OLD's TS-IDMs

Methods: ``tels`` (``recipes/tels_offline.py`` in a subprocess, its run folder
kept at ``<work-dir>/tels/<task>/seed<k>`` and resumed if interrupted),
``iql``, ``td3bc``, ``bc`` (TorchRL's stock losses, ``benchmarks/baselines.py``)
and ``iql_latent`` (IQL on the latents of the TS-IDM of the TELS run with the
same task, seed and TS-IDM budget; if there is none, a TS-IDM is trained by
the recipe alone under ``<work-dir>/tsidm/``). ``--work-dir`` (default
``runs/benchmarks``, git-ignored) holds those run folders and wandb logs: on a
cluster, put it and ``--results-dir`` on storage every job shares. Every method gets the same
policy-step budget (``--steps``, the paper's 100k by default), batch 256 and
evaluation protocol (``--eval-interval``, ``--eval-episodes``, final score =
mean of the last 10 evaluations).
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import os
import shlex
import shutil
import statistics
import sys
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path
from typing import NamedTuple

import torch
import yaml

from benchmarks.baselines import (ADROIT_HYPERPARAMETERS, check_reward_scale, HYPERPARAMETERS, MAZE_HYPERPARAMETERS,
                                  METHODS as BASELINES, train_baseline)
from benchmarks.harness import (code_version, invocation, machine_description, recipe_config, REPO, repo_relative, run_recipe,
                                save_figure, skip_existing, with_pinned_precision, write_result)
from torchrl_tels.errors import CheckpointError
from torchrl_tels.record import second_half_mean
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.training import write_text

DEFAULT_RESULTS = REPO / "benchmarks" / "results"
#: the default grid at longer budgets: ``--table`` on the default results sets it beside them unless --longer says
DEFAULT_LONGER = (DEFAULT_RESULTS / "long20k", DEFAULT_RESULTS / "long50k")
DEFAULT_WORK = REPO / "runs" / "benchmarks"
#: grids of other rows, each in a folder of its own under the default results (their TELS column is the current
#: default, where the default grid's is the paper's reading): ``--table`` renders their TABLE.md and links them
SUB_GRIDS = {
    "heldout": "Table 1's five other locomotion rows, the pre-registered test of the defaults",
    "antmaze100k": "Table 1's AntMaze medium and large rows at 100k transitions",
}

#: TELS with a reduced TS-IDM (paper Table 3): ``tels_<variant>`` trains with ``tsidm.ablation=<variant>``.
ABLATIONS = {"tels_ae": "ae", "tels_dyn": "dyn", "tels_ode": "ode"}
GRID_METHODS = ("tels", *BASELINES)  # tels first: iql_latent reuses its TS-IDM; ablations only on request
#: TELS variants that change stage 2 only, as recipe overrides. ``tels_alpha0``: uniform guide weights (α = 0 in
#: Eq. 10), the best maze variant found on umaze. Their stage 1 is the default's, so a run can start stage 2 from
#: the default run's TS-IDM (``--tsidm-from <its work dir> --tsidm-from-method tels``).
STAGE2_VARIANTS = {"tels_alpha0": ("guide.alpha=0",)}
#: TELS run by the recipe: the default, the paper's reading (domain=paper, or adroit_paper on Adroit), ablations,
#: stage-2 variants
TELS_METHODS = ("tels", "tels_paper", *ABLATIONS, *STAGE2_VARIANTS)
METHODS = (*GRID_METHODS, "tels_paper", *ABLATIONS, *STAGE2_VARIANTS)
TASKS = (
    "hopper-medium-v2-10k",
    "hopper-medium-replay-v2-10k",
    "halfcheetah-medium-v2-10k",
    "walker2d-medium-v2-10k",
)
#: Table 1's other five locomotion rows: nothing was tuned on them, so their first grid is a pre-registered test
#: of the defaults (``--grid --task`` these)
HELD_OUT_TASKS = (
    "hopper-medium-expert-v2-10k",
    "walker2d-medium-replay-v2-10k",
    "walker2d-medium-expert-v2-10k",
    "halfcheetah-medium-replay-v2-10k",
    "halfcheetah-medium-expert-v2-10k",
)
#: Table 1's AntMaze medium and large rows (``load_dataset`` finds them in a data folder)
ANTMAZE_100K_TASKS = (
    "antmaze-medium-diverse-v2-100k",
    "antmaze-medium-play-v2-100k",
    "antmaze-large-diverse-v2-100k",
    "antmaze-large-play-v2-100k",
)
SEEDS = (0, 1, 2)
LABELS = {"bc": "BC", "td3bc": "TD3+BC", "iql": "IQL", "iql_latent": "IQL (TS-IDM latent)", "tels": "TELS",
          "tels_paper": "TELS (paper's reading)", "tels_ae": "φ/ψ + h_inv", "tels_dyn": "↑ + h_fwd, h_rvs", "tels_ode": "↑ + ℓ_ode",
          "tels_alpha0": "TELS (α = 0)", "tsrl": "TSRL"}
TABLE_COLUMNS = ("bc", "td3bc", "iql", "iql_latent", "tels", "tels_paper", *STAGE2_VARIANTS)

#: TELS paper, Table 1: normalized score, mean and std over 5 seeds (final 10 evaluations), same 10k sets.
PAPER_TABLE1 = {
    "hopper-medium-v2-10k": {"bc": (29.7, 11.7), "td3bc": (40.1, 18.6), "iql": (46.7, 6.5),
                             "tsrl": (62.0, 3.7), "tels": (77.3, 10.7)},
    "hopper-medium-replay-v2-10k": {"bc": (12.1, 5.3), "td3bc": (7.3, 6.1), "iql": (13.4, 3.1),
                                    "tsrl": (21.8, 8.2), "tels": (43.2, 3.5)},
    "halfcheetah-medium-v2-10k": {"bc": (26.4, 7.3), "td3bc": (16.4, 10.2), "iql": (29.9, 0.12),
                                  "tsrl": (38.4, 3.1), "tels": (40.8, 0.6)},
    "walker2d-medium-v2-10k": {"bc": (15.8, 14.1), "td3bc": (7.4, 13.1), "iql": (22.5, 3.8),
                               "tsrl": (49.7, 10.6), "tels": (62.4, 5.3)},
    "hopper-medium-expert-v2-10k": {"bc": (27.8, 10.7), "td3bc": (17.8, 7.9), "iql": (34.3, 8.7),
                                    "tsrl": (50.9, 8.6), "tels": (100.9, 6.8)},
    "halfcheetah-medium-replay-v2-10k": {"bc": (14.3, 7.8), "td3bc": (17.9, 9.5), "iql": (22.7, 6.4),
                                         "tsrl": (28.1, 3.5), "tels": (33.2, 1.0)},
    "halfcheetah-medium-expert-v2-10k": {"bc": (19.1, 9.4), "td3bc": (15.4, 10.7), "iql": (10.5, 8.8),
                                         "tsrl": (39.9, 21.1), "tels": (40.7, 1.2)},
    "walker2d-medium-replay-v2-10k": {"bc": (1.4, 1.9), "td3bc": (5.7, 5.8), "iql": (10.7, 11.9),
                                      "tsrl": (26.0, 11.3), "tels": (54.8, 6.0)},
    "walker2d-medium-expert-v2-10k": {"bc": (21.7, 8.2), "td3bc": (7.9, 9.1), "iql": (26.5, 8.6),
                                      "tsrl": (46.4, 17.4), "tels": (87.4, 13.3)},
    "antmaze-umaze-v0-10k": {"bc": (44.7, 42.1), "td3bc": (0.7, 1.2), "iql": (65.1, 19.4),
                             "tsrl": (76.1, 15.6), "tels": (88.7, 7.7)},
    "antmaze-umaze-diverse-v0-10k": {"bc": (24.1, 22.2), "td3bc": (16.27, 16.4), "iql": (34.6, 18.5),
                                     "tsrl": (52.2, 22.1), "tels": (60.9, 16.9)},
    # Table 1's AntMaze medium and large rows, on 100k-transition samples of D4RL's 1M sets
    "antmaze-medium-diverse-v2-100k": {"bc": (0.0, None), "td3bc": (0.0, None), "iql": (4.8, 5.9),
                                       "tsrl": (0.0, None), "tels": (47.2, 17.3)},
    "antmaze-medium-play-v2-100k": {"bc": (0.0, None), "td3bc": (0.0, None), "iql": (12.5, 5.4),
                                    "tsrl": (0.0, None), "tels": (62.9, 17.8)},
    "antmaze-large-diverse-v2-100k": {"bc": (0.0, None), "td3bc": (0.0, None), "iql": (3.6, 4.1),
                                      "tsrl": (0.0, None), "tels": (39.8, 14.1)},
    "antmaze-large-play-v2-100k": {"bc": (0.0, None), "td3bc": (0.0, None), "iql": (3.5, 4.1),
                                   "tsrl": (0.0, None), "tels": (47.3, 13.1)},
    # Table 1 (door-human, 5k transitions: BC and IQL without a std there) and Table 6 (10k of expert data)
    "door-human-v1": {"bc": (0.5, None), "td3bc": (0.5, None), "iql": (4.3, None), "tsrl": (0.5, 0.3),
                      "tels": (11.8, 1.6)},
    "pen-expert-v1-10k": {"bc": (27.6, 21.3), "td3bc": (5.2, 2.7), "iql": (68.9, 24.3), "tsrl": (65.6, 22.8),
                          "tels": (105.7, 12.1)},
    "door-expert-v1-10k": {"bc": (1.2, 1.1), "td3bc": (5.2, 3.1), "iql": (79.2, 8.8), "tsrl": (46.3, 12.5),
                           "tels": (101.8, 8.5)},
    "hammer-expert-v1-10k": {"bc": (0.2, 0.1), "td3bc": (0.5, 0.2), "iql": (70.3, 30.3), "tsrl": (77.6, 31.2),
                             "tels": (91.5, 25.9)},
    "relocate-expert-v1-10k": {"bc": (0.6, 0.1), "td3bc": (0.1, 0.1), "iql": (31.1, 8.4), "tsrl": (45.2, 15.3),
                               "tels": (85.6, 12.1)},
}
#: Task-name prefixes run with the recipe's maze domain (stochastic guide, AntMaze values, r - 1)
#: and the baselines' maze hyperparameters.
MAZE_PREFIXES = ("antmaze", "pointmaze")
#: Task-name prefixes run with the recipe's Adroit domain and the baselines' Adroit hyperparameters.
ADROIT_PREFIXES = ("pen-", "door-", "hammer-", "relocate-")
PAPER_POLICY_STEPS = 100_000  # Table 11
PAPER_TSIDM_EPOCHS = 1000  # Table 10
EVAL_LAST_N = 10  # Table 1: final 10 evaluations
BATCH_SIZE = 256

# torchrl's TD3BCLoss warns about its own attribute annotations at construction; nothing to act on.
warnings.filterwarnings("ignore", message=r".*wasn't part of the annotations.*")


# ------------------------------------------------------------------ paths
def is_maze(task: str) -> bool:
    return task.startswith(MAZE_PREFIXES)


#: the grid's Adroit TELS runs under ``domain=adroit``'s former α (1, the ``mujoco`` domain's departure): a results
#: folder of its own under the grid's, beside ``long20k``
ADROIT_ALPHA1 = "adroit_alpha1"
#: the grid's Adroit TELS runs under ``domain=adroit``'s former MuJoCo departures (β = 0.01, the proposal
#: re-encoded), α = 0.01: a results folder of its own under the grid's
ADROIT_DEPARTURES = "adroit_mujoco_departures"


def is_adroit(task: str) -> bool:
    return task.startswith(ADROIT_PREFIXES)


def domain_hyperparameters(method: str, task: str) -> dict:
    """The baseline's overrides for ``task``'s domain: the maze or the Adroit values, none on locomotion."""
    if is_maze(task):
        return MAZE_HYPERPARAMETERS.get(method, {})
    return ADROIT_HYPERPARAMETERS.get(method, {}) if is_adroit(task) else {}


def result_path(results_dir: Path, method: str, task: str, seed: int) -> Path:
    return results_dir / method / task / f"seed{seed}.json"


def tels_run_dir(work_dir: Path, task: str, seed: int, method: str = "tels") -> Path:
    return work_dir / method / task / f"seed{seed}"


def reused_tsidm_of(record: dict, method: str) -> bool:
    """Whether a grid run started stage 2 from the TS-IDM of a ``method`` run: the TS-IDM it reused lies in
    :func:`tels_run_dir` of that method (``--tsidm-from``, ``--tsidm-from-method``)."""
    source = (record.get("tsidm_reused") or {}).get("from")
    return source is not None and Path(source).parent.parts[-3:-2] == (method,)


# --------------------------------------------------------------- running
def one_command(args, method: str, task: str, seed: int) -> list[str]:
    """The single-run command that reproduces (method, task, seed) with this invocation's budget
    (run from the repository root)."""
    cmd = [sys.executable, "-m", "benchmarks.run_grid", f"--method={method}", f"--task={task}",
           f"--seed={seed}", f"--steps={args.steps}", f"--eval-interval={args.eval_interval}",
           f"--eval-episodes={args.eval_episodes}", f"--results-dir={args.results_dir}",
           f"--work-dir={args.work_dir}"]
    if args.tsidm_steps is not None:
        cmd.append(f"--tsidm-steps={args.tsidm_steps}")
    if args.eval_batched:
        cmd.append("--eval-batched")
    if args.device != "auto":
        cmd.append(f"--device={args.device}")
    if args.threads:
        cmd.append(f"--threads={args.threads}")
    if args.tsidm_from is not None:
        cmd.append(f"--tsidm-from={args.tsidm_from}")
    if args.tsidm_from_method is not None:
        cmd.append(f"--tsidm-from-method={args.tsidm_from_method}")
    # JSON reads back as YAML with the same value and type (str() would turn 1e-05 and None into strings)
    cmd += [f"--set={key}={value if isinstance(value, str) else json.dumps(value)}" for key, value in args.set.items()]
    return cmd


def _recipe_overrides(task: str, seed: int, run_dir: Path, args, wandb_mode: str, method: str = "tels") -> list[str]:
    overrides = [f"dataset.name={task}", f"seed={seed}", f"run_dir={run_dir}", "resume=true",
                 f"logger.wandb_mode={wandb_mode}", f"logger.exp_name=tels_{task}_seed{seed}"]
    if is_maze(task):
        overrides += ["domain=maze", "budget=paper"]
    elif is_adroit(task):
        overrides += ["domain=adroit_paper" if method == "tels_paper" else "domain=adroit", "budget=paper"]
    elif method == "tels_paper":
        overrides += ["domain=paper"]
    if args.tsidm_steps is not None:
        overrides.append(f"tsidm.steps={args.tsidm_steps}")
    return overrides


def run_tels(task: str, seed: int, args, wandb_mode: str, method: str = "tels") -> dict:
    run_dir = tels_run_dir(args.work_dir, task, seed, method)
    if args.force and run_dir.exists():
        shutil.rmtree(run_dir)
    overrides = _recipe_overrides(task, seed, run_dir, args, wandb_mode, method) + [
        f"policy.steps={args.steps}", f"policy.batch_size={BATCH_SIZE}", f"eval.interval={args.eval_interval}",
        f"eval.episodes={args.eval_episodes}", f"eval.last_n={EVAL_LAST_N}", f"eval.batched={args.eval_batched}",
        f"device={args.device}",
    ]
    if method in ABLATIONS:
        overrides += [f"tsidm.ablation={ABLATIONS[method]}", f"logger.exp_name={method}_{task}_seed{seed}"]
    if method in STAGE2_VARIANTS:
        overrides += [*STAGE2_VARIANTS[method], f"logger.exp_name={method}_{task}_seed{seed}"]
    reused = None
    started_from = _recorded_checkpoint(run_dir)
    if started_from is not None:  # an interrupted or finished run resumes with the TS-IDM it started from
        overrides.append(f"tsidm.checkpoint={started_from}")
    elif args.tsidm_from is not None:
        source = tels_run_dir(args.tsidm_from, task, seed, args.tsidm_from_method or method)
        reused = reusable_tsidm(source, task, overrides)
        if reused is not None:
            overrides.append(f"tsidm.checkpoint={reused['from']}")
    run_recipe(overrides, args.threads)
    results = RunFolder(run_dir).read_results()
    record = {**results, "run_dir": str(run_dir), "recipe_overrides": overrides}
    if reused is not None or started_from is not None:
        record["tsidm_reused"] = reused or {"from": started_from,
                                            "beta_results": _tsidm_metadata(Path(started_from)).get("beta_results", [])}
    return record


def _saved_config(run_dir: Path) -> dict | None:
    """The ``config.yaml`` a recipe run wrote in ``run_dir``, ``None`` if there is none or it does not parse."""
    try:
        saved = RunFolder(run_dir).read_config()
    except (CheckpointError, OSError, yaml.YAMLError):
        return None
    return saved if isinstance(saved, dict) else None


def _recorded_checkpoint(run_dir: Path) -> str | None:
    """The ``tsidm.checkpoint`` a run folder's config records, where a run started there (``None`` otherwise)."""
    saved = _saved_config(run_dir) if RunFolder(run_dir).state_path.exists() else None
    return ((saved or {}).get("tsidm") or {}).get("checkpoint")


def _tsidm_metadata(tsidm_path: Path) -> dict:
    """What a TS-IDM file records of its stage 1 (β, dataset, each candidate β's final losses), ``{}`` if unreadable."""
    from torchrl_tels.checkpoint import load_checkpoint
    from torchrl_tels.modules import TSIDM

    try:
        return dict(load_checkpoint(tsidm_path, TSIDM.CHECKPOINT_FORMAT).get("metadata", {}))
    except CheckpointError:
        return {}


def reusable_tsidm(source: Path, task: str, overrides: list[str]) -> dict | None:
    """``source``'s TS-IDM, as ``{"from": path, "beta_results": its stage-1 losses}``, where that run trained it
    itself with the stage-1 settings ``overrides`` give; else ``None``, and why (``--tsidm-from``). Stage 2 then
    starts from it as if this run had trained it."""
    from torchrl_tels.config import stage1_differences, training_config

    def refuse(why: str) -> None:
        print(f"--tsidm-from: {why}; this run trains its own TS-IDM", flush=True)

    saved, tsidm = _saved_config(source), RunFolder(source).tsidm_path
    if saved is None or not tsidm.exists():
        return refuse(f"no finished stage 1 in {source}")
    if (saved.get("tsidm") or {}).get("checkpoint"):
        return refuse(f"{source} did not train its TS-IDM: it started from {saved['tsidm']['checkpoint']}")
    differences = stage1_differences(saved, training_config(recipe_config(with_pinned_precision(overrides))))
    if differences:
        return refuse(f"{source}'s stage 1 had other settings ({'; '.join(differences)})")
    metadata = _tsidm_metadata(tsidm)
    if not metadata.get("beta_results") or metadata.get("dataset") != task or (
            metadata.get("beta") != saved["tsidm"].get("beta") and saved["tsidm"].get("beta") != "auto"):
        return refuse(f"{tsidm} is not the TS-IDM the stage 1 of {RunFolder(source).config_path} wrote")
    return {"from": str(tsidm), "beta_results": metadata["beta_results"]}


def _tsidm_matches(run_dir: Path, task: str, seed: int, tsidm_steps: int | None) -> bool:
    """Whether the recipe run in ``run_dir`` trained its TS-IDM for this task and seed with this budget."""
    cfg = _saved_config(run_dir)
    return (cfg is not None and cfg.get("seed") == seed and cfg.get("dataset", {}).get("name") == task
            and cfg.get("tsidm", {}).get("steps") == tsidm_steps and not cfg.get("tsidm", {}).get("checkpoint"))


def resolve_tsidm(task: str, seed: int, args) -> tuple[Path, str]:
    """The TS-IDM for iql_latent: the TELS run's if it has the same budget, else one the recipe trains alone."""
    tels_dir = tels_run_dir(args.work_dir, task, seed)
    if RunFolder(tels_dir).tsidm_path.exists() and _tsidm_matches(tels_dir, task, seed, args.tsidm_steps):
        return RunFolder(tels_dir).tsidm_path, "TELS run"
    budget = f"steps{args.tsidm_steps}" if args.tsidm_steps is not None else f"epochs{PAPER_TSIDM_EPOCHS}"
    run_dir = args.work_dir / "tsidm" / task / f"seed{seed}_{budget}"
    if not RunFolder(run_dir).tsidm_path.exists():
        # Stage 1 only: the policy stage is cut to one step with a one-step evaluation.
        run_recipe(_recipe_overrides(task, seed, run_dir, args, "disabled") + [
            "policy.steps=1", "eval.interval=1", "eval.episodes=1", "eval.max_steps=1", "eval.last_n=1",
        ], args.threads)
    return RunFolder(run_dir).tsidm_path, "recipe, stage 1 only"


def budget_of(args, method: str) -> dict:
    budget = {"policy_steps": args.steps, "batch_size": BATCH_SIZE, "eval_interval": args.eval_interval,
              "eval_episodes": args.eval_episodes, "eval_last_n": EVAL_LAST_N, "eval_batched": args.eval_batched,
              "paper_policy_steps": PAPER_POLICY_STEPS}
    if method in ("iql_latent", *TELS_METHODS):
        budget["tsidm_steps"] = args.tsidm_steps  # None: the recipe's default, Table 10's 1000 epochs
        budget["paper_tsidm_epochs"] = PAPER_TSIDM_EPOCHS
    return budget


def run_one(method: str, task: str, seed: int, args) -> Path:
    out = result_path(args.results_dir, method, task, seed)
    if skip_existing(out, args.force):
        return out
    wandb_mode = args.wandb_mode
    started = datetime.now(timezone.utc)
    start = time.perf_counter()
    print(f"== {method} {task} seed {seed}: {args.steps} policy steps", flush=True)
    if method in TELS_METHODS:
        results = run_tels(task, seed, args, wandb_mode, method)
        threads = args.threads or torch.get_num_threads()  # the recipe starts with the same default
    else:
        tsidm_path = source = None
        if method == "iql_latent":
            tsidm_path, source = resolve_tsidm(task, seed, args)
        logger = None
        if wandb_mode != "disabled":
            from torchrl_tels.record import RunLogger

            logger = RunLogger(args.work_dir / method / task / f"seed{seed}", f"{method}_{task}_seed{seed}",
                               wandb_mode=wandb_mode,
                               config={"method": method, "task": task, "seed": seed, **budget_of(args, method)})
        results = train_baseline(
            method, task, steps=args.steps, seed=seed, batch_size=BATCH_SIZE, eval_interval=args.eval_interval,
            eval_episodes=args.eval_episodes, eval_last_n=EVAL_LAST_N, eval_batched=args.eval_batched,
            threads=args.threads, device=args.device,
            tsidm_path=tsidm_path, log_fn=logger.log_scalars if logger else None,
            hyperparameters={**domain_hyperparameters(method, task), **args.set},
        )
        if method == "iql_latent":
            results["tsidm"]["source"] = source
        if logger is not None:
            logger.log_scalars({"final_normalized_score_mean": results["final_normalized_score_mean"]}, args.steps)
            logger.close()
        threads = results["torch_threads"]
    record = {
        **results,
        "method": method,
        "task": task,
        "seed": seed,
        "command": shlex.join(one_command(args, method, task, seed)),
        "argv": invocation(),
        "date": started.isoformat(timespec="seconds"),
        "elapsed_s": time.perf_counter() - start,
        "machine": machine_description(),
        "code": code_version(),
        "torch_threads": threads,
        "budget": {**results.get("budget", {}), **budget_of(args, method)},
    }
    if write_result(out, record, args.force):
        print(f"== {method} {task} seed {seed}: final normalized score "
              f"{record['final_normalized_score_mean']:.1f} -> {repo_relative(out)}", flush=True)
    return out


def combos(args):
    methods = [m for m in METHODS if m in (args.method or GRID_METHODS)]
    for seed in args.seed or SEEDS:
        for task in args.task or TASKS:
            for method in methods:
                yield method, task, seed


# ------------------------------------------------------------------- table
def load_results(results_dir: Path) -> dict:
    """{task: {method: [record, ...]}} from every ``<method>/<task>/seed<k>.json``."""
    found: dict[str, dict[str, list]] = {}
    for method in METHODS:
        for path in sorted((results_dir / method).glob("*/seed*.json")):
            try:
                record = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError) as err:
                print(f"warning: skipping unreadable {path}: {err}", file=sys.stderr)
                continue
            found.setdefault(path.parent.name, {}).setdefault(method, []).append(record)
    return found


def _mean_std(values: list[float]) -> tuple[float, float]:
    return statistics.fmean(values), statistics.pstdev(values)


def _steps_label(steps: int) -> str:
    return f"{steps // 1000}k" if steps >= 1000 and steps % 1000 == 0 else str(steps)


def _evaluation_counts_differ(by_method: dict) -> bool:
    return len({len(r["evaluations"]) for runs in by_method.values() for r in runs}) > 1


def row_score(by_method: dict):
    """How a row's cells read each run: the run's own final score (the mean of its last ``eval.last_n``
    evaluations) where every run of the row has the same number of evaluations; where the numbers differ, the
    last 10 would cover all of one run's curve and half of another's, so every run of the row is read over the
    later half of its evaluations (:func:`torchrl_tels.record.second_half_mean`, Table 1's last 10 of 20)."""
    if _evaluation_counts_differ(by_method):
        return lambda run: second_half_mean(run["evaluations"])
    return lambda run: run["final_normalized_score_mean"]


def _budget_cell(by_method: dict) -> str:
    every_run = [r for runs in by_method.values() for r in runs]
    policy = sorted({r["budget"]["policy_steps"] for r in every_run})
    protocol = sorted({(r["budget"]["eval_interval"], r["budget"]["eval_episodes"]) for r in every_run})
    tsidm = sorted({str(r["budget"].get("tsidm_steps")) for m, runs in by_method.items()
                    if m in ("iql_latent", *TELS_METHODS) for r in runs})
    if len(policy) > 1:
        text = "**budgets differ: " + ", ".join(_steps_label(s) for s in policy) + " steps**"
    else:
        text = f"{_steps_label(policy[0])} steps"
        if policy[0] < PAPER_POLICY_STEPS:
            text += f" (below the paper's {_steps_label(PAPER_POLICY_STEPS)})"
    if len(protocol) > 1:
        text += "; **evaluation protocols differ: " + ", ".join(f"{e} ep. every {i}" for i, e in protocol) + "**"
    else:
        text += f"; eval {protocol[0][1]} ep. every {_steps_label(protocol[0][0])}"
    if _evaluation_counts_differ(by_method):
        text += "; **each run read over the later half of its evaluations**"
    if tsidm:
        shown = [f"{PAPER_TSIDM_EPOCHS} epochs" if s == "None" else f"{s} steps" for s in tsidm]
        text += "; TS-IDM " + " / ".join(shown)
        if any(s != "None" for s in tsidm):
            text += f" (paper: {PAPER_TSIDM_EPOCHS} epochs)"
    return text


def _changed_hyperparameters(found: dict) -> list[str]:
    """A line naming each baseline hyperparameter that differs from ``benchmarks/baselines.py``'s default for
    its task (e.g. from ``--set``), so a table of changed baselines says so; nothing when none differ."""
    changed = set()
    for task, by_method in found.items():
        for method in BASELINES:
            default = _baseline_defaults(method, task)
            for run in by_method.get(method, []):
                changed |= {f"{LABELS[method]} `{key}={value}`" for key, value in run.get("hyperparameters", {}).items()
                            if key != "source" and key in default and default[key] != value}
    if not changed:
        return []
    return [f"**Changed from the baselines' defaults:** {', '.join(sorted(changed))}.", ""]


def hyperparameter_section() -> list[str]:
    """Each baseline's settings in each domain, with its ``source`` (where each value comes from, and why a
    departure was made), as ``benchmarks/baselines.py`` defines them."""
    lines = ["## The baselines' settings, per domain, and why", ""]
    for domain, overrides in (("locomotion", {}), ("AntMaze", MAZE_HYPERPARAMETERS), ("Adroit", ADROIT_HYPERPARAMETERS)):
        for method in ("bc", "td3bc", "iql"):
            hp = {**HYPERPARAMETERS[method], **overrides.get(method, {})}
            settings = ", ".join(f"`{k}={v}`" for k, v in hp.items() if k != "source")
            lines.append(f"- **{LABELS[method]}, {domain}**: {settings}. Source and reasons: {hp['source']}.")
    return [*lines, ""]


def paper_cell(value: tuple) -> str:
    mean, std = value
    return f"{mean:.1f}" + (f" ± {std:.1f}" if std is not None else "")


def render_table(results_dir: Path, longer_dirs: tuple[Path, ...] = ()) -> Path:
    """``results_dir``/TABLE.md and its PNGs; ``longer_dirs`` hold the same grid at longer budgets."""
    found = load_results(results_dir)
    longer = {folder: load_results(folder) for folder in longer_dirs}
    tasks = [t for t in TASKS if t in found] + sorted(t for t in found if t not in TASKS)
    # a stage-2 variant gets a column only in a grid that ran it
    columns = [m for m in TABLE_COLUMNS if m not in STAGE2_VARIANTS or any(m in found[t] for t in tasks)]
    lines = [
        "# TELS against TorchRL's offline baselines on Table 1's reduced-size D4RL sets",
        "",
        f"Generated {datetime.now(timezone.utc).isoformat(timespec='seconds')} by "
        f"`python -m benchmarks.run_grid --table` from `{repo_relative(results_dir)}`.",
        "",
        "D4RL normalized score: per seed, the mean of the last 10 evaluations (each of `eval_episodes` "
        "deterministic episodes; in a row whose runs have different numbers of evaluations, the later half of "
        "each run's, as the budget column says); each cell is the mean ± std over seeds (population std), n = seeds, then "
        "the TELS paper's Table 1 value (mean ± std over 5 seeds, 100k policy steps). "
        "Every method of a row has the same data, evaluation env, protocol and policy-step budget.",
        "",
        *_changed_hyperparameters(found),
        "| task | budget | " + " | ".join(LABELS[m] for m in columns) + " | TSRL (paper) |",
        "|---|---|" + "---|" * (len(columns) + 1),
    ]
    for task in tasks:
        paper, score = PAPER_TABLE1.get(task, {}), row_score(found[task])
        cells = []
        for method in columns:
            runs = found[task].get(method, [])
            ours = "—"
            if runs:
                mean, std = _mean_std([score(r) for r in runs])
                ours = f"**{mean:.1f}** ± {std:.1f} (n={len(runs)})" if len(runs) > 1 else f"**{mean:.1f}** (n=1)"
            ref = paper_cell(paper[method]) if method in paper else "—"
            cells.append(f"{ours} · paper {ref}")
        tsrl = paper_cell(paper["tsrl"]) if "tsrl" in paper else "—"
        lines.append(f"| {task} | {_budget_cell(found[task])} | " + " | ".join(cells) + f" | {tsrl} |")
    if not tasks:
        lines.append("| (no results yet) |" + " |" * (len(columns) + 2))
    sub_grids = [(name, what) for name, what in SUB_GRIDS.items() if (results_dir / name / "TABLE.md").is_file()]
    if sub_grids:
        lines += ["", "Other rows, each grid with a table of its own (their TELS column is the default as it stands): "
                  + "; ".join(f"[{what}]({name}/TABLE.md)" for name, what in sub_grids) + "."]
    adroit_tels = [r for t in tasks if is_adroit(t) for r in found[t].get("tels", [])]
    if adroit_tels and (results_dir / ADROIT_DEPARTURES).is_dir():
        reused = sum(reused_tsidm_of(r, "tels_paper") for r in adroit_tels)
        lines += ["", f"Adroit's TELS column holds runs of `domain=adroit` as it stands, the paper's values for other "
                  f"tasks (β selected, Eq. 9, α = 0.01): {reused} of its {len(adroit_tels)} runs started stage 2 from "
                  "the TS-IDM of the same seed's paper's-reading run (`--tsidm-from-method tels_paper`; the same "
                  f"stage-1 settings). The domain's earlier runs, with MuJoCo's departures, are in "
                  f"`{ADROIT_DEPARTURES}/`, and with α = 1 as well in `{ADROIT_ALPHA1}/`; `study/REPORT.md` sets them "
                  "side by side (\"Where the guide's proposals go on Adroit\", \"The paper's reading on Adroit\")."]

    ablation_tasks = [t for t in tasks if any(m in found[t] for m in ABLATIONS)]
    if ablation_tasks:
        variants = (*ABLATIONS, "tels")
        lines += ["", "## TS-IDM ablations (paper Table 3)", "",
                  "TELS with TS-IDM variants: the inverse-dynamics autoencoder alone (`tsidm.ablation=ae`), "
                  "plus latent forward/reverse dynamics (`dyn`), plus ℓ_ode (`ode`), and the full TS-IDM "
                  "(plus ℓ_Tsym). The paper's Table 3 uses the medium-expert sets, which are not among the "
                  "shared data; its hopper-medium-expert row reads 17.2, 35.5, 61.4, 100.9.", "",
                  "| task | budget | " + " | ".join(LABELS[m] for m in variants[:-1]) + " | full TS-IDM |",
                  "|---|---|" + "---|" * len(variants)]
        for task in ablation_tasks:
            cells = []
            for method in variants:
                scores = [r["final_normalized_score_mean"] for r in found[task].get(method, [])]
                if scores:
                    mean, std = _mean_std(scores)
                    cells.append(f"**{mean:.1f}** ± {std:.1f} (n={len(scores)})")
                else:
                    cells.append("—")
            ablation_budget = _budget_cell({m: r for m, r in found[task].items() if m in variants})
            lines.append(f"| {task} | {ablation_budget} | " + " | ".join(cells) + " |")

    lines += ["", "## Speed", "",
              "Training steps per second, evaluation excluded (median over runs; TELS: the policy stage, "
              "and its TS-IDM stage apart), with torch's thread count and the machine each was measured on.",
              "", "| method | torch threads | machine | runs | policy steps/s | TS-IDM steps/s |",
              "|---|---|---|---|---|---|"]
    groups: dict[tuple, list] = {}
    for task in tasks:
        for method, runs in found[task].items():
            for r in runs:
                machine = r.get("machine", {})
                key = (METHODS.index(method), method, r.get("torch_threads"),
                       f"{machine.get('cpu_count')} CPUs, {machine.get('platform', '?')}")
                groups.setdefault(key, []).append(r)
    for (_, method, threads, machine), runs in sorted(groups.items(), key=lambda kv: (kv[0][0], str(kv[0][2:]))):
        policy = [r["steps_per_s"]["policy_excluding_eval"] for r in runs
                  if r.get("steps_per_s", {}).get("policy_excluding_eval")]
        tsidm = [r["steps_per_s"]["tsidm"] for r in runs if r.get("steps_per_s", {}).get("tsidm")]
        policy_cell = f"{statistics.median(policy):.1f}" if policy else "—"
        tsidm_cell = f"{statistics.median(tsidm):.1f}" if tsidm else "—"
        lines.append(f"| {LABELS[method]} | {threads or 'default'} | {machine} | {len(runs)} | {policy_cell} | "
                     f"{tsidm_cell} |")

    lines += aggregate_section(found, results_dir / "plots", longer)
    lines += flatness_section(found, tasks)
    lines += longer_budget_section(found, longer, tasks, results_dir)
    lines += longest_budget_section(found, longer, tasks, results_dir)
    lines += hyperparameter_section()
    plots = render_plots(found, tasks, results_dir / "plots")
    if plots:
        lines += ["", "## Figures", ""] + [f"![{p.stem}](plots/{p.name})" for p in plots]
    lines += ["", "Each result JSON holds its command, date, machine, thread count, budget and "
              "hyperparameters; `python -m benchmarks.run_grid --table` rebuilds this file.", ""]
    out = results_dir / "TABLE.md"
    write_text(out, "\n".join(lines))
    return out


#: The sets the aggregate pools: the four shared D4RL 10k locomotion sets.
AGGREGATE_TASKS = ("hopper-medium-v2-10k", "hopper-medium-replay-v2-10k", "walker2d-medium-v2-10k",
                   "halfcheetah-medium-v2-10k")


def score_matrix(found: dict, method: str, tasks=AGGREGATE_TASKS):
    """``[seeds, tasks]`` final scores of ``method`` for the seeds every task has, or ``None``."""
    import numpy as np

    by_task = [{r["seed"]: r["final_normalized_score_mean"] for r in found.get(t, {}).get(method, [])} for t in tasks]
    seeds = sorted(set.intersection(*(set(d) for d in by_task))) if by_task else []
    if not seeds:
        return None
    return np.array([[d[s] for d in by_task] for s in seeds])


_AGGREGATE_HEADER = ("| method | seeds × tasks | IQM [95 % CI] | mean [95 % CI] |", "|---|---|---|---|")


def _interval_estimates(matrices: dict) -> dict:
    """{label: [(IQM, low, high), (mean, low, high)]} of each ``[seeds, tasks]`` score matrix.

    One seed per task leaves the bootstrap nothing to resample, so such a matrix gets no interval
    (low and high NaN) rather than a point posing as one."""
    from torchrl_tels import stats

    def estimate(scores, statistic):
        if scores.shape[0] == 1:
            return statistic(scores), math.nan, math.nan
        return stats.stratified_bootstrap_ci(scores, statistic)

    return {label: [estimate(scores, statistic) for statistic in (stats.iqm, stats.mean)]
            for label, scores in matrices.items()}


def _aggregate_rows(matrices: dict, estimates: dict) -> list[str]:
    rows = []
    for label, scores in matrices.items():
        cells = [f"**{p:.1f}** (one seed: no interval)" if math.isnan(lo) else f"**{p:.1f}** [{lo:.1f}, {hi:.1f}]"
                 for p, lo, hi in estimates[label]]
        rows.append(f"| {label} | {scores.shape[0]} × {scores.shape[1]} | {cells[0]} | {cells[1]} |")
    return rows


def aggregate_section(found: dict, folder: Path, longer: dict[Path, dict] | None = None) -> list[str]:
    """IQM and mean over tasks × seeds with stratified-bootstrap 95 % intervals (``torchrl_tels.stats``),
    as a table and a PNG with the performance profiles; a method run at a longer budget on all four sets
    (``longer``) gets a row of its own."""
    def runs_of(grid: dict, method: str) -> list[dict]:
        return [r for t in AGGREGATE_TASKS for r in grid.get(t, {}).get(method, [])]

    grids = [found, *(longer or {}).values()]
    # a TELS method whose grids trained their TS-IDMs at different β: each row says its β
    beta_differs = {m for m in TABLE_COLUMNS if m in TELS_METHODS
                    and _differing_hyperparameters([r for g in grids for r in runs_of(g, m)], m, "")}

    def beta_of(runs: list[dict]) -> str:
        return ", β = " + " / ".join(f"{b:g}" for b in sorted({r["beta"] for r in runs if "beta" in r}))

    matrices = {LABELS[m] + (beta_of(runs_of(found, m)) if m in beta_differs else ""): score_matrix(found, m)
                for m in TABLE_COLUMNS}
    for longer_dir, longer_found in (longer or {}).items():
        for method in TABLE_COLUMNS:
            steps = {r["budget"]["policy_steps"] for r in runs_of(longer_found, method)}
            if not steps:
                continue
            label = f"{LABELS[method]} at " + " / ".join(_steps_label(n) for n in sorted(steps)) + " steps"
            if method in beta_differs:
                label += beta_of(runs_of(longer_found, method))
            if label in matrices:  # two folders at one budget: say which is which
                label += f" ({repo_relative(longer_dir)})"
            matrices[label] = score_matrix(longer_found, method)
    matrices = {label: x for label, x in matrices.items() if x is not None}
    if not matrices:
        return []
    lines = ["", "## Aggregate over the four shared sets", "",
             "Interquartile mean (IQM) and mean of the final scores over tasks × seeds, with 95 % "
             "stratified-bootstrap intervals (2,000 resamples of each task's seeds; `torchrl_tels/stats.py`, "
             "rliable's definitions). Only seeds present on all four sets enter; a row without a budget is at "
             "the grid's (see the table above).", "",
             *_AGGREGATE_HEADER]
    estimates = _interval_estimates(matrices)
    lines += _aggregate_rows(matrices, estimates)
    path = _aggregate_plot(matrices, estimates, folder)
    return lines + ["", f"![aggregate](plots/{path.name})"]


#: A curve counts as flat when the least-squares line through the second half of its evaluations (seed mean),
#: with twice its standard error either side, moves less than this many points across that half.
FLAT_POINTS = 2.0


def second_half_fit(runs: list[dict]) -> tuple[list[int], list[float], float, float] | None:
    """``(steps, seed-mean scores, slope per 1k steps, its standard error)`` of a least-squares line over the
    second half of the evaluation steps every run shares, or ``None`` with fewer than five shared
    evaluations, so that the half has at least three points and the line a scatter to measure."""
    import numpy as np

    curves = [{e["step"]: e["score"] for e in r.get("evaluations", [])} for r in runs]
    steps = sorted(set.intersection(*(set(c) for c in curves))) if curves else []
    late = steps[len(steps) // 2:]
    if len(late) < 3:
        return None
    means = [statistics.fmean(c[s] for c in curves) for s in late]
    x, y = np.array(late) / 1000.0, np.array(means)
    slope, intercept = np.polyfit(x, y, 1)
    residuals = y - (slope * x + intercept)
    spread = float(((x - x.mean()) ** 2).sum())
    return late, means, float(slope), math.sqrt((residuals**2).sum() / (len(x) - 2) / spread)


def scatter_over_episode_noise(runs: list[dict], fit) -> float | None:
    """How much of the scatter about the second half's line (:func:`second_half_fit`) the sampling of
    episodes explains: the line's residual variance over the variance each seed-mean point would have from
    its episodes alone (each run's episode variance over its episode count, summed over runs, over runs²).
    Near 1, evaluation noise makes the band, and more episodes per evaluation would narrow it. Well above 1,
    the policy itself changes from one evaluation to the next (or the curve bends): more episodes do not
    average that away; more seeds or more evaluations do. ``None`` without per-episode scores."""
    if fit is None:
        return None
    late, _, _, se = fit
    x = [s / 1000.0 for s in late]
    residual_var = se**2 * sum((v - statistics.fmean(x)) ** 2 for v in x)
    point_vars = []
    for step in late:
        episodes = [e.get("scores") or [] for r in runs for e in r["evaluations"] if e["step"] == step]
        if any(len(scores) < 2 for scores in episodes):
            return None
        point_vars.append(sum(statistics.variance(s) / len(s) for s in episodes) / len(episodes) ** 2)
    noise_var = statistics.fmean(point_vars)
    return residual_var / noise_var if noise_var > 0 else None


def curve_verdict(runs: list[dict]) -> tuple[str, str, bool]:
    """``(slope cell, verdict, flat)`` for the seed-mean curve of ``runs``: the second half's least-squares
    slope per 1k steps and how far that line moves across the half, ± twice its standard error (the band).
    Flat when the line and its band stay within :data:`FLAT_POINTS` (``|move| + band``); otherwise still
    rising or falling where the band excludes no move, and "no trend detected" where it does not: the
    evaluations are too noisy to tell a flat curve from a moving one."""
    return _verdict_of_fit(second_half_fit(runs))


def _verdict_of_fit(fit) -> tuple[str, str, bool]:
    """:func:`curve_verdict` of a :func:`second_half_fit` already computed."""
    if fit is None:
        return "—", "too few evaluations", False
    late, _, slope, se = fit
    span = (late[-1] - late[0]) / 1000.0
    rise, band = slope * span, 2 * se * span
    flat = abs(rise) + band < FLAT_POINTS
    if flat:
        verdict = "flat"
    elif abs(rise) > band:
        verdict = "**still rising**" if rise > 0 else "**still falling**"
    else:
        verdict = "no trend detected"
    return f"{slope:+.2f} ({rise:+.1f} ± {band:.1f} across it)", verdict, flat


def flatness_section(found: dict, tasks: list[str]) -> list[str]:
    """Has each method's learning curve flattened at its budget? The slope of a least-squares line through
    the last half of its evaluations (seed-mean score against step), per 1k steps."""
    rows = []
    for task in tasks:
        for method in TABLE_COLUMNS:
            fit = second_half_fit(found[task].get(method, []))
            if fit is None:
                continue
            late, means, _, _ = fit
            slope_cell, verdict, _ = _verdict_of_fit(fit)
            ratio = scatter_over_episode_noise(found[task][method], fit)
            rows.append(f"| {task} | {LABELS[method]} | {_steps_label(late[-1])} | {len(found[task][method])} | "
                        f"{means[0]:.1f} → {means[-1]:.1f} | {slope_cell} | {verdict} | "
                        + ("—" if ratio is None else f"{ratio:.1f}") + " |")
    if not rows:
        return []
    return ["", "## Have the learning curves flattened?", "",
            "For each method and set: the seed-mean evaluation score over the second half of training, the "
            "slope of a least-squares line through it (points per 1k steps) with how far it moves across the "
            "half ± twice its standard error, and the verdict (flat when the move "
            f"and its band stay within {FLAT_POINTS:g} points). The last column divides the scatter about that "
            "line by the part of it that the sampling of episodes explains: near 1, more episodes per "
            "evaluation would narrow the band; well above 1, the policy changes from one evaluation to the "
            "next, which more episodes do not average away (more seeds do).", "",
            "| task | method | budget | seeds | second half: first → last evaluation | slope per 1k | verdict "
            "| scatter / episode noise |",
            "|---|---|---|---|---|---|---|---|", *rows]


def _score_cell(runs: list[dict]) -> str:
    return _mean_cell([r["final_normalized_score_mean"] for r in runs])


def _mean_cell(scores: list[float]) -> str:
    """Mean ± population std over seeds, with n; "—" for none."""
    if not scores:
        return "—"
    mean, std = _mean_std(scores)
    return f"**{mean:.1f}** ± {std:.1f} (n={len(scores)})" if len(scores) > 1 else f"**{mean:.1f}** (n=1)"


def longer_budget_section(found: dict, longer: dict[Path, dict], tasks: list[str], results_dir: Path) -> list[str]:
    """Each method at this grid's budget beside the same method, task and protocol at a longer budget (the
    ``--longer`` folders), with the longer curve's second-half slope and whether it is flat
    (:data:`FLAT_POINTS`): the budget a baseline needs before its score can be compared."""
    rows = []
    for folder, longer_found in longer.items():
        for task in [t for t in tasks if t in longer_found] + sorted(t for t in longer_found if t not in tasks):
            for method in TABLE_COLUMNS:
                longer_runs = longer_found[task].get(method, [])
                if not longer_runs:
                    continue
                runs_here = found.get(task, {}).get(method, [])
                slope_cell, verdict, _ = curve_verdict(longer_runs)
                differ = _differing_hyperparameters(runs_here + longer_runs, method, task)
                if differ:
                    verdict += f"; **hyperparameters differ: {', '.join(differ)}**"
                rows.append(f"| {task} | {LABELS[method]} | {_budget_cell({method: runs_here}) if runs_here else '—'} | "
                            f"{_score_cell(runs_here)} | {_budget_cell({method: longer_runs})} | "
                            f"{_score_cell(longer_runs)} | {slope_cell} | {verdict} | "
                            f"[{repo_relative(folder)}]({_link(folder, results_dir)}) |")
    if not rows:
        return []
    return ["", "## Each method at this budget and at a longer one", "",
            "The same method, set and evaluation protocol at this table's budget and at a longer budget "
            "(`--longer` folders of `run_grid` results). The slope is that of a least-squares line through the "
            "second half of the longer run's seed-mean curve, per 1k steps, and how far that line moves across "
            "the half, ± twice its standard error from the scatter about the line (the band); *flat* means the "
            f"move and its band stay within {FLAT_POINTS:g} points, *still rising/falling* that the band excludes "
            "no move, *no trend detected* that the band holds no move but is too wide to call the curve flat. "
            "A score compares methods only where the curve behind it is flat.", "",
            "| task | method | budget | score | longer budget | score | second half: slope per 1k | "
            "verdict | results |", "|---|---|---|---|---|---|---|---|---|", *rows]


class LongestPick(NamedTuple):
    """One method on one set at the longest budget it was run at (:func:`longest_budget_picks`)."""
    steps: int  # its policy steps
    label: str  # the budget as the table names it (with folder and protocol where two share the steps)
    runs: list  # its result records, one per seed
    verdict: str  # the verdict on that budget's curve (:func:`curve_verdict`), markdown emphasis included
    flat: bool
    tried: list  # [(steps, label, runs, (verdict, flat))] of every budget run, shortest first
    differ: list  # hyperparameter names whose values differ between its runs


def longest_budget_picks(found: dict, longer: dict[Path, dict], tasks: list[str],
                         results_dir: Path) -> dict[tuple[str, str], LongestPick]:
    """``{(task, method): pick}``: each method on each set at the longest budget it was run at, among this grid's
    (``found``, from ``results_dir``) and the ``--longer`` folders' (at equal budgets, the folder named last).
    Runs group by budget and evaluation protocol, so a pick never mixes two protocols."""
    grids = [(results_dir, found), *longer.items()]
    picks = {}
    for task in tasks + sorted({t for g in longer.values() for t in g} - set(tasks)):
        for method in TABLE_COLUMNS:
            groups: dict[tuple, list] = {}
            for i, (grid_dir, grid) in enumerate(grids):
                for r in grid.get(task, {}).get(method, []):
                    if not r.get("evaluations"):
                        print(f"warning: {LABELS[method]} {task} seed {r.get('seed')} in {repo_relative(grid_dir)} "
                              "has no evaluations; left out", file=sys.stderr)
                        continue
                    budget = r["budget"]
                    groups.setdefault((budget["policy_steps"], i, budget["eval_interval"], budget["eval_episodes"]),
                                      []).append(r)
            if not groups:
                continue
            several = {steps for steps, *_ in groups if sum(k[0] == steps for k in groups) > 1}
            tried = []
            for (steps, i, interval, episodes), runs in sorted(groups.items()):
                label = _steps_label(steps)
                if steps in several:  # say which folder and protocol
                    label += f" ({repo_relative(grids[i][0])}, {episodes} ep. every {_steps_label(interval)})"
                tried.append((steps, label, runs, curve_verdict(runs)[1:]))
            steps, label, runs, (verdict, flat) = tried[-1]
            picks[task, method] = LongestPick(steps, label, runs, verdict, flat, tried,
                                              _differing_hyperparameters(runs, method, task))
    return picks


def longest_budget_matrices(picks: dict[tuple[str, str], LongestPick]) -> dict:
    """``{label: [seeds, tasks] second-half scores}`` over the four shared sets, one per method picked on all
    four, its label naming the budgets and every verdict but flat (:func:`longest_budget_section`'s aggregate)."""
    import numpy as np

    matrices = {}
    for method in TABLE_COLUMNS:
        if not all((task, method) in picks for task in AGGREGATE_TASKS):
            continue
        by_task = [{r["seed"]: second_half_mean(r["evaluations"]) for r in picks[task, method].runs}
                   for task in AGGREGATE_TASKS]
        seeds = sorted(set.intersection(*(set(d) for d in by_task)))
        if not seeds:
            continue
        budgets = sorted({picks[task, method].steps for task in AGGREGATE_TASKS})
        verdicts = collections.Counter(picks[task, method].verdict.strip("*") for task in AGGREGATE_TASKS)
        label = (f"{LABELS[method]} at " + " / ".join(_steps_label(b) for b in budgets) + " steps"
                 + "".join(f", {verdict} on {n} of {len(AGGREGATE_TASKS)}"
                           for verdict, n in sorted(verdicts.items()) if verdict != "flat")
                 + (", **hyperparameters differ**" if any(picks[t, method].differ for t in AGGREGATE_TASKS) else ""))
        matrices[label] = np.array([[d[s] for d in by_task] for s in seeds])
    return matrices


def longest_budget_section(found: dict, longer: dict[Path, dict], tasks: list[str], results_dir: Path) -> list[str]:
    """Each method on each set at the longest budget it was run at (:func:`longest_budget_picks`), with every
    budget's verdict on its curve (:func:`curve_verdict`): the longest, because a curve flat over a short run can
    still move later. The score is the second-half mean (:func:`torchrl_tels.record.second_half_mean`), so that
    budgets with different numbers of evaluations are read alike. Then the aggregate over the four shared sets
    (:func:`longest_budget_matrices`), with the same intervals as :func:`aggregate_section` and a PNG of its own."""
    picks = longest_budget_picks(found, longer, tasks, results_dir)
    rows = []
    for (task, method), pick in picks.items():
        read_at = pick.label + ("" if pick.flat else f" ({pick.verdict})")
        if pick.differ:
            read_at += f"; **hyperparameters differ: {', '.join(pick.differ)}**"
        rows.append(f"| {task} | {LABELS[method]} | " + " · ".join(f"{t[1]}: {t[3][0]}" for t in pick.tried)
                    + f" | {read_at} | {_mean_cell([second_half_mean(r['evaluations']) for r in pick.runs])} |")
    if not rows:
        return []
    lines = ["", "## Each method at its longest budget", "",
             "Each method on each set at the longest budget it was run at, among this table's and the "
             "`--longer` folders', with the verdict on the curve at every budget run (as in the section above: "
             "flat when the second half's least-squares line, ± twice its standard error, moves less than "
             f"{FLAT_POINTS:g} points). A score is converged where the "
             "longest curve is flat; where it is not, the row gives the verdict. The score is the mean of each seed's "
             "later half of evaluations (Table 1's last 10 of 20, whatever the number of evaluations), "
             "mean ± std over seeds.", "",
             "| task | method | budgets run: verdict | read at | second-half score |", "|---|---|---|---|---|",
             *rows]
    matrices = longest_budget_matrices(picks)
    if not matrices:
        return lines
    estimates = _interval_estimates(matrices)
    lines += ["", "Over the four shared sets, each method at those budgets (second-half scores; seeds present on "
              "all four sets):", "", *_AGGREGATE_HEADER, *_aggregate_rows(matrices, estimates)]
    path = _aggregate_plot(matrices, estimates, results_dir / "plots", "aggregate_longest_budget.png")
    return lines + ["", f"![aggregate at the longest budgets](plots/{path.name})"]


def _differing_hyperparameters(runs: list[dict], method: str, task: str) -> list[str]:
    """The hyperparameter names whose values are not the same in every run, a name a run does not record
    read as the baselines' default for the task, so a row never compares two settings unawares."""
    if method in TELS_METHODS:  # TELS records the β its TS-IDM trained at, the setting its grids have changed
        recorded = [{"tsidm.beta": r["beta"]} for r in runs if "beta" in r]
    else:
        defaults = _baseline_defaults(method, task)
        recorded = [{**defaults, **r["hyperparameters"]} for r in runs if r.get("hyperparameters")]
    return sorted({key for hp in recorded for key in hp if key != "source"
                   and any(other.get(key) != hp[key] for other in recorded)})


def _baseline_defaults(method: str, task: str) -> dict:
    """``benchmarks/baselines.py``'s hyperparameters for ``method`` on ``task`` (none for TELS)."""
    if method not in BASELINES:
        return {}
    return {**HYPERPARAMETERS[method], **domain_hyperparameters(method, task)}


def _link(folder: Path, results_dir: Path) -> str:
    """``folder``'s TABLE.md relative to ``results_dir``'s, for a markdown link."""
    return Path(os.path.relpath(folder / "TABLE.md", results_dir)).as_posix()


def _aggregate_plot(matrices: dict, estimates: dict, folder: Path, filename: str = "aggregate.png") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchrl_tels import stats

    fig, (ax_ci, ax_profile) = plt.subplots(1, 2, figsize=(10, 3.8))
    methods = list(matrices)
    for row, method in enumerate(methods):
        for col, (name, (point, low, high)) in enumerate(zip(("IQM", "mean"), estimates[method])):
            y = row + (0.15 if col else -0.15)
            ax_ci.plot([low, high], [y, y], color=f"C{col}", linewidth=4, alpha=0.6,  # NaN: no bar
                       label=name if row == 0 else None)
            ax_ci.plot([point], [y], "k|", markersize=10)
    ax_ci.set_yticks(range(len(methods)), methods)
    ax_ci.set_xlabel("D4RL normalized score")
    ax_ci.set_title("95 % stratified-bootstrap intervals")
    ax_ci.legend(fontsize=8)
    taus = np.linspace(0, max(float(x.max()) for x in matrices.values()) * 1.05, 100)
    for method in methods:
        ax_profile.plot(taus, stats.performance_profile(matrices[method], taus), label=method)
    ax_profile.set_xlabel("score τ")
    ax_profile.set_ylabel("fraction of runs × tasks above τ")
    ax_profile.set_title("performance profiles")
    ax_profile.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, folder / filename)


def render_plots(found: dict, tasks: list[str], folder: Path) -> list[Path]:
    """A grouped bar chart per task (ours ± std over seeds, paper values as markers) and learning curves."""
    if not tasks:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    methods = [m for m in TABLE_COLUMNS if any(m in found[t] for t in tasks)]
    colors = {m: f"C{i}" for i, m in enumerate(TABLE_COLUMNS)}
    fig, ax = plt.subplots(figsize=(max(6, 2.2 * len(tasks)), 4))
    width = 0.8 / max(len(methods), 1)
    score_of = {task: row_score(found[task]) for task in tasks}
    for i, method in enumerate(methods):
        xs, means, stds, paper_xs, paper_ys = [], [], [], [], []
        for j, task in enumerate(tasks):
            x = j + (i - (len(methods) - 1) / 2) * width
            runs = found[task].get(method, [])
            if runs:
                mean, std = _mean_std([score_of[task](r) for r in runs])
                xs.append(x), means.append(mean), stds.append(std)
            if method in PAPER_TABLE1.get(task, {}):
                paper_xs.append(x), paper_ys.append(PAPER_TABLE1[task][method][0])
        ax.bar(xs, means, width, yerr=stds, capsize=3, color=colors[method], label=LABELS[method])
        ax.scatter(paper_xs, paper_ys, marker="_", s=250, color="black", zorder=3,
                   label="paper Table 1" if i == 0 else None)
    ax.set_xticks(range(len(tasks)), [t.replace("-v2-10k", "") for t in tasks], fontsize=8)
    ax.set_ylabel("D4RL normalized score")
    ax.set_title("final score (bars: ours, mean ± std over seeds; black: paper Table 1)", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    paths.append(save_figure(fig, folder / "scores_by_task.png"))
    plt.close(fig)

    # Fig. 4 (left) of the paper: the same IQL on raw states and on TS-IDM latents, seeds as dots.
    if all(any(m in found[t] for t in tasks) for m in ("iql", "iql_latent")):
        fig, ax = plt.subplots(figsize=(max(5, 1.8 * len(tasks)), 3.5))
        labelled = set()
        for i, method in enumerate(("iql", "iql_latent")):
            for j, task in enumerate(tasks):
                scores = [r["final_normalized_score_mean"] for r in found[task].get(method, [])]
                if not scores:
                    continue
                x = j + (i - 0.5) * 0.4
                mean, std = _mean_std(scores)
                ax.bar(x, mean, 0.4, yerr=std, capsize=3, color=colors[method],
                       label=None if method in labelled else LABELS[method])
                ax.scatter([x] * len(scores), scores, s=10, color="black", zorder=3)
                labelled.add(method)
        ax.set_xticks(range(len(tasks)), [t.replace("-v2-10k", "") for t in tasks], fontsize=8)
        ax.set_ylabel("D4RL normalized score")
        ax.set_title("IQL on raw states vs on TS-IDM latents (dots: seeds)", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(save_figure(fig, folder / "iql_latent_vs_raw.png"))
        plt.close(fig)

    for task in tasks:
        fig, ax = plt.subplots(figsize=(7, 4))
        for method in TABLE_COLUMNS:
            runs = found[task].get(method, [])
            by_step: dict[int, list[float]] = {}
            for r in runs:
                for e in r.get("evaluations", []):
                    by_step.setdefault(e["step"], []).append(e["score"])
            if not by_step:
                continue
            steps = sorted(by_step)
            stats = [_mean_std(by_step[s]) for s in steps]
            mean = [m for m, _ in stats]
            ax.plot(steps, mean, color=colors[method], label=f"{LABELS[method]} (n={len(runs)})")
            ax.fill_between(steps, [m - s for m, s in stats], [m + s for m, s in stats], color=colors[method],
                            alpha=0.2)
        ax.set_title(f"{task}: evaluations during training (mean ± std over seeds)", fontsize=9)
        ax.set_xlabel("policy training step")
        ax.set_ylabel("D4RL normalized score")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(save_figure(fig, folder / f"curves_{task}.png"))
        plt.close(fig)
    return paths


# --------------------------------------------------------------------- CLI
def _split(values: list[str] | None) -> list[str] | None:
    """``--seed 0 1``, ``--seed 0,1`` and repeated ``--seed=0 --seed=1`` all give ["0", "1"]."""
    if not values:
        return None
    return [v for value in values for v in value.split(",") if v]


def _parse_set_pairs(parser, pairs: list[str], methods, results_dir: Path) -> dict:
    """``--set KEY=VALUE`` pairs as a dict, each key a hyperparameter of every baseline among ``methods`` and
    each value read as YAML, then as a number where the default is one (YAML reads ``3e-4`` as a string)."""
    chosen = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            parser.error(f"--set takes KEY=VALUE, got {pair!r}")
        chosen[key] = yaml.safe_load(value)
    if not chosen:
        return chosen
    if any(m not in BASELINES for m in methods):
        parser.error("--set applies to the baselines only; give --method among " + ", ".join(BASELINES))
    if results_dir == DEFAULT_RESULTS.resolve():
        parser.error("--set changes a baseline, so its runs need their own --results-dir (a result that exists "
                     "is skipped whatever its hyperparameters)")
    for method in methods:
        unknown = sorted(set(chosen) - set(HYPERPARAMETERS[method]))
        if unknown:
            parser.error(f"--set: {method} has no hyperparameter(s) {unknown}")
    defaults = {key: HYPERPARAMETERS[methods[0]][key] for key in chosen}
    for key, value in chosen.items():
        numeric_default = isinstance(defaults[key], (int, float)) and not isinstance(defaults[key], bool)
        if numeric_default and isinstance(value, str):
            try:
                chosen[key] = float(value)
            except ValueError:
                pass
    if "reward_scale" in chosen:
        try:
            check_reward_scale(chosen["reward_scale"])
        except ValueError as err:
            parser.error(f"--set: {err}")
    return chosen


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[2:]))
    # Every option also takes the underscore spelling, the form a wandb sweep parameter gives (--key=value).
    parser.add_argument("--method", "--methods", action="extend", nargs="+", metavar="M",
                        help=f"one of {', '.join(METHODS)} (several with --grid/--list; default all)")
    parser.add_argument("--task", "--tasks", action="extend", nargs="+", metavar="T",
                        help="a dataset name (several with --grid/--list; default the four 10k locomotion sets)")
    parser.add_argument("--seed", "--seeds", action="extend", nargs="+", metavar="K",
                        help="a seed (several with --grid/--list; default 0 1 2)")
    parser.add_argument("--steps", type=int, default=PAPER_POLICY_STEPS,
                        help="policy gradient steps, the same for every method (default: the paper's 100000)")
    parser.add_argument("--tsidm-steps", "--tsidm_steps", type=int, default=None,
                        help="TS-IDM steps for tels/iql_latent (default: the recipe's 1000 epochs, Table 10)")
    parser.add_argument("--eval-interval", "--eval_interval", type=int, default=5000)
    parser.add_argument("--eval-episodes", "--eval_episodes", type=int, default=10)
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N (auto: CUDA where there is one)")
    parser.add_argument("--eval-batched", "--eval_batched", action="store_true",
                        help="run each evaluation's episodes as one batch of envs (the grid's results ran "
                             "them one at a time, which this keeps by default)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch intra-op threads (and OMP_NUM_THREADS of the recipe); default: torch's")
    parser.add_argument("--results-dir", "--results_dir", type=Path, default=DEFAULT_RESULTS)
    parser.add_argument("--work-dir", "--work_dir", type=Path, default=DEFAULT_WORK,
                        help="TELS run folders, TS-IDM files, wandb logs (default: runs/benchmarks)")
    parser.add_argument("--tsidm-from", "--tsidm_from", type=Path, default=None, metavar="WORK_DIR",
                        help="a --work-dir of an earlier grid: each TELS run starts stage 2 from the TS-IDM of "
                             "its run there (same method, task and seed) where that stage 1 had the same "
                             "settings, e.g. to rerun stage 2 after one of its defaults changed")
    parser.add_argument("--tsidm-from-method", "--tsidm_from_method", choices=TELS_METHODS, default=None,
                        metavar="M", help="with --tsidm-from: the TS-IDMs of this method's runs there (default: "
                                          "the same method), e.g. when a domain's default takes its paper's values")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a baseline hyperparameter (benchmarks/baselines.py), e.g. reward_scale=return_range; "
                             "recorded in the result, so give such runs their own --results-dir (repeatable)")
    parser.add_argument("--force", action="store_true", help="redo runs whose result exists")
    parser.add_argument("--wandb-mode", "--wandb_mode", choices=("online", "offline", "disabled"),
                        default="online" if os.environ.get("WANDB_SWEEP_ID") else "disabled",
                        help="wandb logging of each run (default: online inside a wandb sweep, else disabled)")
    parser.add_argument("--grid", action="store_true", help="run every missing (method, task, seed), in turn")
    parser.add_argument("--list", action="store_true", help="print one command per missing run and exit")
    parser.add_argument("--table", action="store_true", help="render TABLE.md and the PNGs from existing results")
    parser.add_argument("--longer", action="append", type=Path, default=[], metavar="DIR",
                        help="with --table: a --results-dir of the same grid at a longer budget, shown beside "
                             "this one with its curves' flatness (repeatable; default for the default "
                             "--results-dir: its long20k and long50k)")
    args = parser.parse_args(argv)
    args.method, args.task = _split(args.method), _split(args.task)
    try:
        args.seed = [int(s) for s in _split(args.seed) or []] or None
    except ValueError:
        parser.error(f"--seed takes integers, got {args.seed}")
    from torchrl_tels.envs import get_task

    for task in args.task or []:
        try:
            get_task(Path(task).stem)
        except ValueError as err:
            parser.error(str(err))
    unknown = sorted(set(args.method or []) - set(METHODS))
    if unknown:
        parser.error(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    if min(args.steps, args.eval_interval, args.eval_episodes) < 1 or (args.tsidm_steps or 1) < 1:
        parser.error("--steps, --tsidm-steps, --eval-interval and --eval-episodes must be positive")
    if args.threads is not None and args.threads < 1:
        parser.error("--threads must be positive")
    args.set = _parse_set_pairs(parser, args.set, args.method or GRID_METHODS, args.results_dir.resolve())
    if args.set.get("reward_scale", 1) != 1 and any(is_maze(t) for t in args.task or []):
        parser.error("--set reward_scale applies to locomotion sets; mazes take the IQL paper's r - 1 instead")
    args.results_dir, args.work_dir = args.results_dir.resolve(), args.work_dir.resolve()
    if args.tsidm_from is not None:
        if not args.tsidm_from.is_dir():
            parser.error(f"--tsidm-from folder not found: {args.tsidm_from}")
        args.tsidm_from = args.tsidm_from.resolve()
        # one work dir may lend one arm's TS-IDMs to another (tels_alpha0 from tels), never a method to itself
        if args.tsidm_from == args.work_dir and (args.tsidm_from_method is None
                                                 or args.tsidm_from_method in (args.method or METHODS)):
            parser.error("--tsidm-from names --work-dir itself: give the earlier grid's work dir, and this grid a "
                         "new one (or, from another arm of this grid, --tsidm-from-method that arm)")
    elif args.tsidm_from_method is not None:
        parser.error("--tsidm-from-method needs --tsidm-from: the earlier grid's work dir")
    args.longer = [folder.resolve() for folder in args.longer]
    if args.table and not args.longer and args.results_dir == DEFAULT_RESULTS.resolve():
        args.longer = [folder for folder in DEFAULT_LONGER if folder.is_dir()]
    missing = [str(folder) for folder in args.longer if not folder.is_dir()]
    if missing:
        parser.error(f"--longer folder(s) not found: {', '.join(missing)}")
    if args.longer and not args.table:
        parser.error("--longer only applies to --table")
    single = not (args.grid or args.list or args.table)
    if single:
        if not (args.method and args.task and args.seed is not None):
            parser.error("one run needs --method, --task and --seed (or use --grid, --list, --table)")
        if len(args.method) > 1 or len(args.task) > 1 or len(args.seed) > 1:
            parser.error("one run takes one --method, --task and --seed; use --grid for several")
    args.single = single
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.single:
        run_one(args.method[0], args.task[0], args.seed[0], args)
        return 0
    if args.list:
        for method, task, seed in combos(args):
            if args.force or not result_path(args.results_dir, method, task, seed).exists():
                print(shlex.join(one_command(args, method, task, seed)))
        return 0
    failed = []
    if args.grid:
        for method, task, seed in combos(args):
            try:
                run_one(method, task, seed, args)
            except KeyboardInterrupt:
                raise
            except Exception as err:  # one failed run must not stop a grid that spans hours
                print(f"!! {method} {task} seed {seed} failed: {type(err).__name__}: {err}", file=sys.stderr)
                failed.append((method, task, seed))
    if args.table:
        print(f"wrote {render_table(args.results_dir, tuple(args.longer))}")
        for folder in args.longer:  # the table above links each longer grid's own TABLE.md, so it stays current
            print(f"wrote {render_table(folder)}")
        if args.results_dir == DEFAULT_RESULTS.resolve():
            for name in SUB_GRIDS:
                if (args.results_dir / name).is_dir():
                    print(f"wrote {render_table(args.results_dir / name)}")
    if failed:
        print(f"{len(failed)} run(s) failed: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
