"""Choices 6 and 7 at action time: the same trained TELS policy acting three ways.

The actor of Eq. (11) feeds the guide's proposal z' straight to h_inv with
h_inv's dropout off. The paper leaves open whether z' should first be decoded
and re-encoded (choice 7) and whether h_inv keeps its training dropout when
acting (choice 6). Neither changes training, so this script takes finished
TELS runs (``runs/benchmarks/tels/<task>/seed<k>``, made by
``python -m benchmarks.run_grid --method tels``) and evaluates each final policy
three ways on the same episode seeds::

    python -m study.action_time --task hopper-medium-v2-10k --seed 0 1 2 --episodes 20

writes ``study/results/action_time/<task>/seed<k>.json``
(temp file + rename; skipped if it exists unless ``--force``). ``--work-dir`` and
``--results-name`` point it at other runs, e.g. the paper-budget ones; ``--runs`` names the
folder of ``run_choice.py`` variants (``--work-dir runs/reproduction --runs latent2x``).
"""
from __future__ import annotations

import argparse
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from benchmarks.harness import invocation, machine_description, REPO, skip_existing, write_result
from torchrl_tels.checkpoint import file_sha256
from torchrl_tels.envs import evaluate_policy, get_task, make_eval_env, normalized_score
from torchrl_tels.modules import load_tels_actor
from torchrl_tels.run_folder import RunFolder

VARIANTS = {
    "eq11": {"reencode_proposal": False, "inverse_dropout": False},  # Eq. (11) as written: the default actor
    "reencode": {"reencode_proposal": True, "inverse_dropout": False},  # choice 7
    "dropout": {"reencode_proposal": False, "inverse_dropout": True},  # choice 6
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--seed", type=int, nargs="+", required=True)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--work-dir", type=Path, default=REPO / "runs" / "benchmarks")
    parser.add_argument("--runs", default="tels", help="folder under --work-dir holding <task>/seed<k> runs; "
                        "e.g. --work-dir runs/reproduction --runs latent2x for run_choice's runs")
    parser.add_argument("--results-name", default="action_time",
                        help="results land in study/results/<this>/<task>/seed<k>.json")
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    task = get_task(args.task)
    for seed in args.seed:
        out = REPO / "study" / "results" / args.results_name / args.task / f"seed{seed}.json"
        if skip_existing(out, args.force):
            continue
        run_dir = args.work_dir / args.runs / args.task / f"seed{seed}"
        folder = RunFolder(run_dir)
        if not folder.policy_path.exists():
            raise SystemExit(f"no finished TELS run in {run_dir}: run python -m benchmarks.run_grid --method tels first")
        env = make_eval_env(task.env_id)  # as the recipe evaluates
        record = {"task": args.task, "seed": seed, "episodes": args.episodes, "run_dir": run_dir,
                  "policy_sha256": file_sha256(folder.policy_path), "tsidm_sha256": file_sha256(folder.tsidm_path),
                  "command": invocation(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  "machine": {**machine_description(), "threads": args.threads}, "variants": {}}
        for name, options in VARIANTS.items():
            start = time.perf_counter()
            torch.manual_seed(seed)  # the dropout masks
            # Loaded after seeding, as when these results were made: building the TS-IDM draws from the RNG.
            actor = load_tels_actor(folder.policy_path, folder.tsidm_path, env.action_spec, **options)
            returns = evaluate_policy(actor, env, args.episodes, seed=2_000_000 + 1000 * seed,
                                      max_steps=task.max_episode_steps)
            scores = [normalized_score(task, r) for r in returns]
            record["variants"][name] = {"options": options, "scores": scores,
                                        "score": sum(scores) / len(scores), "eval_s": time.perf_counter() - start}
            print(f"{args.task} seed {seed} {name}: {record['variants'][name]['score']:.1f}", flush=True)
        write_result(out, record, args.force)


if __name__ == "__main__":
    main()
