"""Does the TS-IDM's forward model, rolled several steps ahead, order one step's alternatives where one step does not?

    python -m study.model_lookahead --run-dir <run> --name <arm>-<task>-seed<k> [--horizon H]
    python -m study.model_lookahead --table

``model_selection`` reads V at the next latent Eq. (6)'s forward model predicts for each candidate: within a
state, its rank with the discounted return that follows the candidate (``local``: its action, then the actor)
is near zero. ``oracle_choice`` finds that what separates the candidates is often a fall hundreds of steps
later, which one step does not reach. The hypothesis here: the forward model, rolled further, carries the
candidates' differences to where V can see them. From each candidate's predicted next latent, the actor
acts in the model, z_{t+1} = z_t + h_fwd(z_t, h_inv(z_t, π_g(z_t))) (Eqs. (6) and (11), no decoding),
and each lookahead L of ``LOOKAHEADS`` scores the candidate by V(z_L). There is no reward model: the rewards
along the way, which can differ between one state's candidates, are not scored.

The reading reports, per L, the median over ``model_selection``'s local start states of the within-state
rank correlation of V(z_L) with the return after (``rank``). Rising with L toward the ceiling
(``model_selection``'s nudged repeat), a model-based lookahead is worth building; flat near zero, the model's
compounding error hides what separates the candidates. ``drift``: how far the model's latent rollout of the
actor's own candidate has moved from its start, per L, the RMS of z_L − z₀ over the data's RMS latent step
(a model that stays put scores its start); ``spread``, the data's own RMS distance of a latent from their mean
in the same unit, against which a drift far larger says the rollout has left the data's latent region.

Writes ``study/results/model_lookahead/<name>.json`` (skipped if it exists unless ``--force``).
"""
from __future__ import annotations

import torch

from benchmarks.harness import REPO
from study.latent_scale import run_results
from study.model_selection import (CANDIDATES, HORIZON_OPTION, LatentActionChoice, local_returns,
                                   own_action, read_candidates, row_spearman)
from study.proposal_cap import reading_main, RUN_FILES
from study.value_delivery import HORIZON
from torchrl_tels.run_folder import RunFolder

RESULTS = REPO / "study" / "results" / "model_lookahead"
COMMAND = "python -m study.model_lookahead"
LOOKAHEADS = (1, 2, 5, 10, 20, 50, 100)


@torch.no_grad()
def lookahead_latents(chooser: LatentActionChoice, predicted: torch.Tensor,
                      lookaheads: tuple[int, ...] | None = None) -> dict[int, torch.Tensor]:
    """``{L: z_L}`` for each L of ``lookaheads`` (``LOOKAHEADS``): from the candidates' predicted next latents
    ``predicted`` (z₁), the actor acting in the forward model, z_{t+1} = z_t + h_fwd(z_t, h_inv(z_t, π_g(z_t)))."""
    lookaheads = LOOKAHEADS if lookaheads is None else lookaheads
    tsidm, latent, out = chooser.tsidm, predicted, {}
    for step in range(1, max(lookaheads) + 1):
        if step > 1:
            latent = latent + tsidm.latent_forward(latent, chooser.own_latent_action(latent))
        if step in lookaheads:
            out[step] = latent
    return out


def rms_distance(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The root mean square over rows of the Euclidean distance between ``x`` and ``y``."""
    return (x - y).pow(2).sum(-1).mean().sqrt()


def model_lookahead(run_dir, horizon: int | None = None) -> dict:
    horizon = HORIZON if horizon is None else horizon
    run, _, data, value, gamma, policy, observation, latent, latent_actions, predicted = read_candidates(run_dir)
    chooser = policy(own_action)
    local, after = local_returns(run, policy, observation, chooser.actions(latent_actions), gamma, horizon)
    with torch.no_grad():
        data_latent = run.tsidm.encode_state(data["observation"])
    data_step = run.data_step_rms  # the data's RMS latent step, the diagnostics' latent_step_rms
    ahead = lookahead_latents(chooser, predicted[:, local])
    start = latent[local]
    return {"final_score": run.results["final_normalized_score_mean"], "horizon": horizon, "states": len(local),
            "candidates": CANDIDATES, "actor_return": after[0].median().item(),
            "spread": rms_distance(data_latent, data_latent.mean(0)).item() / data_step,
            "lookahead": {str(steps): {"rank": row_spearman(value(z).T, after.T).nanmedian().item(),
                                       "drift": rms_distance(z[0], start).item() / data_step}
                          for steps, z in ahead.items()}}


def table(records: dict[tuple[str, str, int], dict] | None = None) -> str:
    records = run_results(RESULTS) if records is None else records
    steps = sorted({int(s) for r in records.values() for s in r["lookahead"]})
    lines = ["| arm | task | seed | run's score | horizon | data's latent spread | "
             + " | ".join(f"rank at L = {s} (drift)" for s in steps) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(steps)]
    for (arm, task, seed), r in sorted(records.items()):
        cells = [f"{r['lookahead'][str(s)]['rank']:.2f} ({r['lookahead'][str(s)]['drift']:.3g})"
                 if str(s) in r["lookahead"] else "—" for s in steps]
        spread = f"{r['spread']:.1f}" if "spread" in r else "—"
        lines.append(f"| {arm} | {task} | {seed} | {r['final_score']:.1f} | {r['horizon']} | {spread} "
                     f"| {' | '.join(cells)} |")
    return "\n".join(lines)


def _summary(record: dict) -> str:
    return "rank with the return after, by lookahead: " + ", ".join(
        f"L={steps} {reading['rank']:.2f}" for steps, reading in record["lookahead"].items())


def main(argv=None) -> None:
    reading_main(argv, prog=COMMAND, description=__doc__.splitlines()[0], results=RESULTS, read=model_lookahead,
                 table=table, summary=_summary, required=(*RUN_FILES, RunFolder.STATE), options=HORIZON_OPTION)


if __name__ == "__main__":
    main()
