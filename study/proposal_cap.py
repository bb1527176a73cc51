"""Does capping the guide's proposed latent step rescue a run whose proposals leave the data's step scale?

    python -m study.proposal_cap --run-dir <run> --name <arm>-<task>-seed<k> --caps 1 2

re-evaluates a finished recipe run (``config.yaml``, ``tsidm.pt``, ``policy.pt``, ``results.json``) with its own actor
options, once as trained and once per cap k with the guide's step π_g(z) - z scaled down, per state, to at
most k times the RMS latent step √E‖φ_s(s') - φ_s(s)‖² of its training data (no training). Each reading is ten
deterministic episodes, seeded alike for every cap. If proposals far off the data's step scale (the
``proposed / data step`` column of the action-error table) caused a run's low score, a cap would lift it.
Writes ``study/results/proposal_cap/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

from benchmarks.harness import invocation, machine_description, REPO, repo_relative, skip_existing, write_result
from study.action_error import training_rows
from torchrl_tels.checkpoint import load_checkpoint
from torchrl_tels.data import load_dataset
from torchrl_tels.diagnostics import latent_statistics
from torchrl_tels.envs import evaluate_policy, get_task, make_eval_envs, normalized_score, Task
from torchrl_tels.modules import load_tels_actor, make_tels_actor, TSIDM
from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY, POLICY_FORMAT
from torchrl_tels.run_folder import RunFolder

EPISODES = 10
#: What a finished recipe run folder holds that these readings load.
RUN_FILES = (RunFolder.CONFIG, RunFolder.RESULTS, RunFolder.TSIDM, RunFolder.POLICY)


class CappedStep(nn.Module):
    """The guide with its proposed step z' - z scaled down to at most ``max_step`` in norm."""

    def __init__(self, guide: nn.Module, max_step: float):
        super().__init__()
        self.guide, self.max_step = guide, max_step

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        proposal = self.guide(latent)
        step = proposal - latent
        norm = step.norm(dim=-1, keepdim=True)
        # a step within the cap is the guide's own proposal, bit for bit
        return torch.where(norm > self.max_step, latent + step * (self.max_step / norm.clamp_min(1e-12)), proposal)


@dataclass
class FinishedRun:
    """A finished recipe run rebuilt for acting: its TS-IDM, its Eq. (11) actor and evaluation envs."""

    results: dict
    task: Task
    data: TensorDictBase  # the transitions the run trained on
    tsidm: TSIDM
    actor: TensorDictModuleBase
    env: EnvBase
    data_step_rms: float
    seed: int  # of one fixed set of episodes, not any training evaluation's


def load_finished_run(run_dir: Path, episodes: int = EPISODES) -> FinishedRun:
    """Loads ``run_dir`` (``config.yaml``, ``tsidm.pt``, ``policy.pt``, ``results.json``) with ``episodes`` envs."""
    folder = RunFolder(run_dir)
    results, config = folder.read_results(), folder.read_config()
    data = load_dataset(config["dataset"]["name"])
    data, task = data[training_rows(data, config["dataset"], config["seed"])], get_task(results["task"])
    tsidm = TSIDM.load(folder.tsidm_path, observation_dim=data["observation"].shape[-1],
                       action_dim=data["action"].shape[-1]).eval()
    data_step = latent_statistics(tsidm, data["observation"], data["next", "observation"])["latent_step_rms"]
    env = make_eval_envs(task.env_id, episodes)
    actor = load_tels_actor(folder.policy_path, tsidm, env.action_spec_unbatched)
    return FinishedRun(results, task, data, tsidm, actor, env, data_step, results["seed"] * 100_000 + 1)


def check_finished_run(parser: argparse.ArgumentParser, run_dir: Path, required=RUN_FILES) -> None:
    """Exits through ``parser`` naming the first of ``required`` that ``run_dir`` lacks."""
    for name in RunFolder(run_dir).missing(required)[:1]:
        parser.error(f"{run_dir / name} is missing: pass a finished run folder")


def reading_main(argv, *, prog: str, description: str, results: Path, read: Callable[..., dict],
                 table: Callable[[], str], summary: Callable[[dict], str], required=RUN_FILES,
                 options: dict[str, dict] | None = None) -> None:
    """The command line of a reading of finished runs: ``--run-dir``/``--name`` writes
    ``results/<name>.json`` from ``read(run_dir, **options)`` (skipped if it exists unless ``--force``) and
    prints ``summary(record)``; ``--table`` prints ``table()``. ``options``: the reading's own arguments,
    ``{name: argparse keywords}``, passed to ``read`` by name."""
    options = options or {}
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--run-dir", type=Path, help="a finished recipe run")
    for name, keywords in options.items():
        parser.add_argument(f"--{name}", **keywords)
    parser.add_argument("--name", help=f"results land in {repo_relative(results)}/<name>.json")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    parser.add_argument("--table", action="store_true", help="print the table of every reading")
    args = parser.parse_args(argv)
    if args.table:
        print(table())
        return
    if args.run_dir is None or args.name is None:
        parser.error("--run-dir and --name are required (or --table)")
    check_finished_run(parser, args.run_dir, required)
    torch.set_num_threads(args.threads)
    out = results / f"{args.name}.json"
    if skip_existing(out, args.force):
        return
    record = read(args.run_dir, **{name: getattr(args, name) for name in options})
    record.update(run_dir=str(args.run_dir), command=invocation(),
                  date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  machine={**machine_description(), "threads": args.threads})
    print(summary(record))
    write_result(out, record, args.force)


def capped_scores(run_dir: Path, caps: list[float]) -> dict:
    run = load_finished_run(run_dir)
    payload = load_checkpoint(RunFolder(run_dir).policy_path, POLICY_FORMAT)
    if payload["mode"] != "deterministic":
        raise SystemExit(f"error: {run_dir} has a {payload['mode']} guide; the cap applies to a deterministic one")
    guide, options = run.actor[1].module, payload.get("actor_options", {})
    scores = {}
    for cap in [None, *caps]:
        module = guide if cap is None else CappedStep(guide, cap * run.data_step_rms)
        actor = make_tels_actor(run.tsidm, TensorDictModule(module, in_keys=[LATENT_KEY], out_keys=[GUIDE_KEY]),
                                run.env.action_spec_unbatched, **options)
        with torch.no_grad():
            returns = evaluate_policy(actor, run.env, EPISODES, seed=run.seed)
        scores["as trained" if cap is None else f"cap {cap:g}"] = float(
            normalized_score(run.task, torch.tensor(returns)).mean())
    return {"dataset": run.results["dataset"], "final_score": run.results["final_normalized_score_mean"],
            "data_step_rms": run.data_step_rms, "episodes": EPISODES, "scores": scores}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True, help="a finished recipe run")
    parser.add_argument("--name", required=True, help="results land in results/proposal_cap/<name>.json")
    parser.add_argument("--caps", type=float, nargs="+", default=[1.0, 2.0],
                        help="caps on the proposed step, in multiples of the data's RMS latent step")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    args = parser.parse_args(argv)
    if any(cap <= 0 for cap in args.caps):
        parser.error("--caps must be positive")
    check_finished_run(parser, args.run_dir)
    torch.set_num_threads(args.threads)
    out = REPO / "study" / "results" / "proposal_cap" / f"{args.name}.json"
    if skip_existing(out, args.force):
        return
    record = capped_scores(args.run_dir, args.caps)
    record.update(run_dir=str(args.run_dir), command=invocation(),
                  date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  machine={**machine_description(), "threads": args.threads})
    print(", ".join(f"{name} {score:.1f}" for name, score in record["scores"].items()))
    write_result(out, record, args.force)


if __name__ == "__main__":
    main()
