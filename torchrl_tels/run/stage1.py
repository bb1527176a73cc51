"""Algorithm 1, lines 1-4: the TS-IDM trained by Eq. (7), for every seed of a :class:`~torchrl_tels.seeds.SeedAxis`,
with App. B.5's choice of β among candidates, or taken from a pretrained checkpoint."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase

from torchrl_tels.compile import capturable_adam
from torchrl_tels.config import RunSpec, TSIDMSpec
from torchrl_tels.data import make_offline_replay_buffer
from torchrl_tels.modules import TSIDM
from torchrl_tels.objectives import TSIDMLoss
from torchrl_tels.run.data import check_same_stage1_length
from torchrl_tels.run.loop import Cadence, make_train_step, train_loop
from torchrl_tels.run.state import RunState
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.seeds import SeedAxis
from torchrl_tels.training import check_finite_state, FiniteWatch

__all__ = ["SELECTION_KEYS", "TSIDM_TERMS", "adopt_pretrained_tsidm", "fit_tsidm", "load_pretrained_tsidm",
           "make_stage1", "make_tsidm", "make_tsidm_loss", "skip_stage1"]

TSIDM_TERMS = ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym", "ell_total", "ell_sum", "latent_rms", "latent_step_rms")
# App. B.5 picks beta by "the lowest TS-IDM training loss": "unweighted" compares the four terms'
# sum (ell_sum), "weighted" Eq. (7) itself (ell_total), which scales three terms by the candidate.
SELECTION_KEYS = {"unweighted": "final_sum", "weighted": "final_loss"}


def make_tsidm(t: TSIDMSpec, data: TensorDictBase) -> TSIDM:
    """A fresh TS-IDM of Table 10's shape, with state normalization fitted on ``data``."""
    tsidm = TSIDM(
        data["observation"].shape[-1],
        data["action"].shape[-1],
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
    return tsidm


def make_tsidm_loss(t: TSIDMSpec, tsidm: TSIDM, beta: float) -> TSIDMLoss:
    """Eq. (7) with ``beta``, Table 3's ablation, the norm reduction and the latent-scale option."""
    term_weights = dict(t.term_weights) if t.term_weights is not None else None
    return TSIDMLoss(tsidm, beta=beta, ablation=t.ablation, dim_reduction=t.dim_reduction,
                     term_weights=term_weights, relative=t.latent_scale == "relative", check_inputs=False)


def _as_list(value):
    return value.tolist() if torch.is_tensor(value) else value


def fit_tsidm(spec: RunSpec, datas: Sequence[TensorDictBase], beta: float, axis: SeedAxis, run: RunState,
              folder: RunFolder, logger=None) -> list[tuple[TSIDM, dict, dict]]:
    """Stage 1 for one β (Eq. 7) and every seed of ``axis``: per seed, a trained TS-IDM, its final losses and
    its loss history.

    Each seed's networks are built on its own stream, which the caller started (:meth:`SeedAxis.start`). Final
    losses average the last 10 % of steps, which App. B.5's β rule compares. The checkpoints go to ``folder``'s
    state file; a run that stopped inside this β continues from its last one.
    """
    t = spec.tsidm
    total = check_same_stage1_length(t, datas, axis.seeds)
    tsidms, losses, buffers = [], [], []
    for k, data in enumerate(datas):
        with axis.use(k):
            tsidms.append(make_tsidm(t, data).to(spec.device))
            losses.append(make_tsidm_loss(t, tsidms[-1], beta))
            buffers.append(make_offline_replay_buffer(data, t.batch_size, device=spec.device))
    loss = axis.stack(losses)
    optim = capturable_adam(loss.parameters(), lr=t.lr, weight_decay=t.weight_decay, capturable=spec.compile.cudagraphs)
    watch = FiniteWatch(f"stage 1 (TS-IDM, beta={beta:g})", entries=axis.labels)
    start, tail, histories = 0, [], [{key: [] for key in TSIDM_TERMS} for _ in datas]
    if run.resumes("tsidm", run.candidate):
        run.restore(loss=loss, optim=optim, **axis.state_modules())
        start, tail = run.step, run.modules["tail"]
        histories = run.modules.get("histories") or [run.tsidm_history]  # a plain run's older checkpoints
    train_step = make_train_step(loss, optim, spec.precision_context(), spec.compile)

    def update(step: int) -> TensorDictBase:
        out = train_step(axis.sample(buffers))
        watch.update(out, step)
        if step >= int(0.9 * total):  # int(): runs under 10 steps still keep their last step
            tail.append(torch.stack([out["ell_total"], out["ell_sum"]], -1))
        return out

    def log(step: int, out: TensorDictBase) -> dict:
        for k, history in enumerate(histories):
            scalars = {key: axis.of(out[key], k).item() for key in TSIDM_TERMS if key in out.keys()}
            for key, value in scalars.items():
                history[key].append((step, value))
            if logger is not None:
                prefix = f"{axis.prefix(k)}tsidm/"
                logger.log_scalars({**{prefix + key: v for key, v in scalars.items()}, f"{prefix}beta": beta},
                                   step + run.candidate * total)
        return {"loss": f"{out['ell_total'].mean().item():.4f}"}

    def checkpoint(step: int) -> None:
        run.step = step
        run.save(folder.state_path, loss=loss.state_dict(), optim=optim.state_dict(), histories=histories,
                 tail=[_as_list(pair) for pair in tail], **{k: m.state_dict() for k, m in axis.state_modules().items()})

    train_loop(update, start=start, total=total, cadence=Cadence(spec.logger.log_interval, spec.checkpoint.interval),
               desc=f"stage 1: TS-IDM beta={beta:g}" + (f", {len(axis)} seeds" if axis.stacked else ""),
               check_finite=watch.check, log=log, checkpoint=checkpoint)
    if axis.stacked:
        loss.write_back()
    tail = [_as_list(pair) for pair in tail]
    fitted = []
    for k, (data, tsidm) in enumerate(zip(datas, tsidms)):
        label = axis.labels[k] if axis.stacked else f"beta={beta:g}"
        check_finite_state(losses[k].state_dict(), f"stage 1 (TS-IDM, {label}) after step {total}")
        tsidm = tsidm.cpu()  # saved and handed on from the CPU; stage 2 moves it where it trains
        if tsidm.latent_standardization:
            tsidm.fit_latent_standardization(data["observation"])
        pairs = [axis.of(pair, k) for pair in tail]
        final = {key: sum(pair[i] for pair in pairs) / len(pairs) for i, key in enumerate(("final_loss", "final_sum"))}
        fitted.append((tsidm.eval(), final, histories[k]))
    return fitted


def load_pretrained_tsidm(spec: RunSpec, data: TensorDictBase) -> TSIDM | None:
    """The TS-IDM of ``tsidm.checkpoint`` (checked against the data's sizes), or ``None``."""
    if not spec.tsidm.checkpoint:
        return None
    return TSIDM.load(spec.tsidm.checkpoint, observation_dim=data["observation"].shape[-1],
                      action_dim=data["action"].shape[-1])


def skip_stage1(run: RunState) -> None:
    """Moves a run that starts from a pretrained TS-IDM to stage 2, so that its stage-2 checkpoints resume there."""
    if run.stage == "tsidm":
        run.stage, run.candidate, run.step = "policy", 0, 0


def adopt_pretrained_tsidm(spec: RunSpec, pretrained: TSIDM, run: RunState, folders: Sequence[RunFolder]) -> TSIDM:
    """Starts ``run`` at stage 2 from ``tsidm.checkpoint``'s TS-IDM, copied into each of ``folders`` (its source in
    the metadata), so that a run folder holds every model it acted with: export and the readings of finished runs
    load ``tsidm.pt`` from the folder, and the checkpoint may move or change after the run."""
    skip_stage1(run)
    metadata = {**pretrained.metadata, "checkpoint": str(spec.tsidm.checkpoint)}
    for folder in folders:
        pretrained.save(RunFolder(folder).tsidm_path, metadata=metadata)
    return pretrained


def make_stage1(spec: RunSpec, datas: Sequence[TensorDictBase], axis: SeedAxis, run: RunState, folder: RunFolder,
                seed_runs: Sequence[RunState], seed_folders: Sequence[RunFolder], logger=None,
                pretrained: TSIDM | None = None) -> list[TSIDM]:
    """Algorithm 1, lines 1-4, for every seed of ``axis``: the ``pretrained`` TS-IDM, this run's finished stage 1,
    or a trained one, saved as each seed's ``tsidm.pt`` in ``seed_folders``; ``seed_runs`` record each seed's β
    results and history, and ``run`` in ``folder`` where the stage is (a plain run: ``[run]`` and ``[folder]``).

    With ``tsidm.beta=auto`` each candidate is trained and the one with the lowest final
    training loss is kept (App. B.5); finished candidates survive an interruption.
    """
    if pretrained is not None:
        return [adopt_pretrained_tsidm(spec, pretrained, run, seed_folders)] * len(axis)
    if run.stage != "tsidm":
        return [TSIDM.load(seed_folder.tsidm_path, observation_dim=data["observation"].shape[-1],
                           action_dim=data["action"].shape[-1]) for seed_folder, data in zip(seed_folders, datas)]
    t = spec.tsidm
    candidates = list(t.beta_candidates) if t.beta == "auto" else [float(t.beta)]
    key = SELECTION_KEYS[t.beta_selection]
    best: list[tuple | None] = [None] * len(axis)
    with run.time("tsidm_s"):
        for candidate, beta in enumerate(candidates):
            if candidate < len(seed_runs[0].beta_results):
                continue  # finished before an interruption; its model is in best_tsidm.pt
            run.candidate = candidate
            for k, seed in enumerate(axis.seeds):
                axis.start(k, seed + candidate)
            fitted = fit_tsidm(spec, datas, beta, axis, run, folder, logger)
            for k, (model, final, history) in enumerate(fitted):
                seed_runs[k].beta_results.append({"beta": beta, **final})
                print(f"TS-IDM beta={beta:g}: final training loss {final['final_loss']:.5f} (Eq. 7), "
                      f"{final['final_sum']:.5f} (unweighted)")
                if min(r[key] for r in seed_runs[k].beta_results) == final[key]:
                    best[k] = (model, history, beta)
                    model.save(seed_folders[k].best_tsidm_path, metadata={"beta": beta, "history": history})
            run.candidate, run.step = candidate + 1, 0
            for seed_run in seed_runs:
                seed_run.tsidm_history = {}
            run.save(folder.state_path)
    tsidms = []
    for k, (seed_folder, seed_run) in enumerate(zip(seed_folders, seed_runs)):
        if best[k] is None:
            model = TSIDM.load(seed_folder.best_tsidm_path)
            best[k] = (model, model.metadata["history"], model.metadata["beta"])
        tsidm, seed_run.tsidm_history, beta = best[k]
        tsidm.metadata = {"beta": beta, "dataset": str(spec.dataset.name), "beta_results": seed_run.beta_results}
        tsidm.save(seed_folder.tsidm_path, metadata=tsidm.metadata)
        print(f"stage 1 done: beta={beta:g}, TS-IDM saved to {seed_folder.tsidm_path}")
        tsidms.append(tsidm)
    run.stage, run.candidate, run.step = "policy", 0, 0
    run.save(folder.state_path)
    return tsidms
