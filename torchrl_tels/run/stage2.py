"""Algorithm 1, lines 6-8, for every seed of a :class:`~torchrl_tels.seeds.SeedAxis`: the data encoded once by
the frozen φ_s, the latent value (Eq. 8), the guide (Eq. 9/10) trained against the updated V, and the actor of
Eq. (11); :func:`fit_stage2` trains them."""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch
from tensordict import TensorDictBase
from torchrl.objectives import SoftUpdate

from torchrl_tels.compile import capturable_adam, compile_update
from torchrl_tels.config import CompileSpec, RunSpec
from torchrl_tels.data import make_offline_replay_buffer
from torchrl_tels.diagnostics import latent_statistics
from torchrl_tels.envs import TSIDMEncoderTransform
from torchrl_tels.modules import make_guide_policy, make_latent_value, make_tels_actor, TSIDM
from torchrl_tels.objectives import LatentExpectileLoss, TSymGuideLoss
from torchrl_tels.run.loop import Cadence, make_train_step, train_loop
from torchrl_tels.run.state import RunState
from torchrl_tels.run_folder import RunFolder
from torchrl_tels.seeds import SeedAxis
from torchrl_tels.training import FiniteWatch

__all__ = ["SeedStage2", "Stage2", "fit_stage2", "make_seed_stage2", "make_stage2"]


@dataclass
class SeedStage2:
    """One seed's stage 2: its encoded data, V (Eq. 8), guide (Eq. 9/10), their optimizers and its actor (Eq. 11)."""

    buffer: Any
    value_loss: LatentExpectileLoss
    guide_loss: TSymGuideLoss
    value_optim: torch.optim.Optimizer
    guide_optim: torch.optim.Optimizer
    target_updater: SoftUpdate
    actor: Any
    guide: Any
    actor_options: dict
    latent_stats: dict


def make_seed_stage2(spec: RunSpec, data: TensorDictBase, tsidm: TSIDM, action_spec) -> SeedStage2:
    """Freezes the TS-IDM, encodes the data once (Algorithm 1, line 6) and builds V, π_g and the actor."""
    device = spec.device
    tsidm.to(device).eval()
    tsidm.requires_grad_(False)
    data = data.clone().to(device)
    data["next", "reward"] = spec.dataset.reward_scale * data["next", "reward"] + spec.dataset.reward_bias
    buffer = make_offline_replay_buffer(data, spec.policy.batch_size, write_transforms=[TSIDMEncoderTransform(tsidm)],
                                        device=device)
    latent_dim = tsidm.latent_state_dim
    latent_stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    latent_stats["data_action_std"] = data["action"].std(0).mean().item()
    print(f"latent scale: RMS spread {latent_stats['latent_rms']:.4g}, RMS step {latent_stats['latent_step_rms']:.4g}")
    torch.manual_seed(spec.seed + 1000)  # the same networks whether stage 1 ran here or before a resume
    v, g = spec.value, spec.guide
    value_net = make_latent_value(latent_dim, v.num_cells).to(device)
    guide = make_guide_policy(latent_dim, g.mode, g.num_cells).to(device)
    value_loss = LatentExpectileLoss(value_net, expectile=v.expectile, check_inputs=False)
    value_loss.make_value_estimator(gamma=v.gamma)
    guide_loss = TSymGuideLoss(
        guide, value_net, tsidm, mode=g.mode, alpha=g.alpha, eta=g.eta, tsym_regularizer=g.tsym_regularizer,
        tsym_weight=g.tsym_weight, tsym_reference=latent_stats["latent_step_rms"] ** 2 if g.tsym_relative else None,
        reach_weight=g.reach_weight, max_weight=g.max_weight, dim_reduction=spec.tsidm.dim_reduction,
        check_inputs=False,
    )
    guide_loss.make_value_estimator(gamma=v.gamma)
    actor_options = {"reencode_proposal": g.reencode_proposal, "inverse_dropout": g.act_with_dropout}
    return SeedStage2(
        buffer=buffer,
        value_loss=value_loss,
        guide_loss=guide_loss,
        target_updater=SoftUpdate(value_loss, tau=v.target_update_rate),
        value_optim=capturable_adam(value_loss.value_network_params.values(True, True), lr=v.lr,
                                    capturable=spec.compile.cudagraphs),
        guide_optim=capturable_adam(guide_loss.parameters(), lr=g.lr, capturable=spec.compile.cudagraphs),
        actor=make_tels_actor(tsidm, guide, action_spec, **actor_options).to(device),
        guide=guide,
        actor_options=actor_options,
        latent_stats=latent_stats,
    )


def _adam_options(optim: torch.optim.Optimizer) -> dict:
    group = optim.param_groups[0]
    return {key: group[key] for key in ("lr", "betas", "eps", "weight_decay", "fused", "capturable")}


class Stage2:
    """Stage 2 of the seeds of ``axis`` (one :class:`SeedStage2` each), trained as one update.

    A plain run trains its seed's losses and optimizers as they are. A stacked run stacks the seeds' V and guide
    losses; the guide's copy of V is a view of the stacked V, so it reads the updated V as a plain run's guide
    does, the target V follows by the same ``lerp_`` as torchrl's ``SoftUpdate``, and one Adam over the stacked
    leaves is the seeds' own side by side (Adam is elementwise). Call :meth:`write_back` before using a seed's
    own actor, guide or V.
    """

    def __init__(self, stages: Sequence[SeedStage2], axis: SeedAxis, amp: Callable = contextlib.nullcontext,
                 compile: CompileSpec = CompileSpec()):
        self.stages, self.axis = list(stages), axis
        self.amp, self.compile = amp, compile  # the loss forward passes' precision; compile_update's switches
        first = self.stages[0]
        if axis.stacked:
            self.value_loss = axis.stack([stage.value_loss for stage in self.stages])
            self.guide_loss = axis.stack([stage.guide_loss for stage in self.stages])
            self.guide_loss.share("value_network_params", self.value_loss)
            self.value_optim = torch.optim.Adam(self.value_loss.trainable("value_network_params"),
                                                **_adam_options(first.value_optim))
            self.guide_optim = torch.optim.Adam(self.guide_loss.parameters(), **_adam_options(first.guide_optim))
            self.target_weight = 1 - first.target_updater.eps  # SoftUpdate: target.lerp_(source, 1 - eps)
            update_target = self._update_stacked_target
        else:
            self.value_loss, self.guide_loss = first.value_loss, first.guide_loss
            self.value_optim, self.guide_optim = first.value_optim, first.guide_optim
            update_target = first.target_updater.step
        self.value_watch = FiniteWatch("stage 2 (value)", entries=axis.labels)
        self.guide_watch = FiniteWatch("stage 2 (guide)", entries=axis.labels)
        value_step = make_train_step(self.value_loss, self.value_optim, amp, compile, record_graph=False)
        guide_step = make_train_step(self.guide_loss, self.guide_optim, amp, compile, record_graph=False)

        def train_step(batch: TensorDictBase):
            # Algorithm 1, line 7: V by Eq. (8); line 8: the guide against the updated V; then the target V.
            value_losses = value_step(batch)
            guide_losses = guide_step(batch)
            update_target()
            return value_losses, guide_losses

        self.train_step = compile_update(train_step, cudagraphs=compile.cudagraphs)

    def _update_stacked_target(self) -> None:
        params = self.value_loss.params
        params["target_value_network_params"].data.lerp_(params["value_network_params"].data, self.target_weight)

    @property
    def buffer(self):
        """A plain run's encoded data (a stacked run draws through :meth:`sample`)."""
        if self.axis.stacked:
            raise AttributeError("a stacked Stage2 has one buffer per seed: draw batches with sample().")
        return self.stages[0].buffer

    def sample(self) -> TensorDictBase:
        """One batch of encoded data per seed (:meth:`SeedAxis.sample`)."""
        return self.axis.sample([stage.buffer for stage in self.stages])

    def update(self, batch: TensorDictBase, step: int):
        """One step of lines 7-8 for every seed; a stacked run's losses carry a leading seed dimension.

        A non-finite loss is recorded without a host synchronization; :meth:`check_finite`
        raises for it, naming the term and the step."""
        value_losses, guide_losses = self.train_step(batch)
        self.value_watch.update(value_losses, step)
        self.guide_watch.update(guide_losses, step)
        return value_losses, guide_losses

    def check_finite(self) -> None:
        """Raises :class:`NonFiniteLossError` if any loss was not finite since the start."""
        self.value_watch.check()
        self.guide_watch.check()

    def write_back(self) -> None:
        """Copies each seed's stacked slice into its own modules (a plain run trains them in place)."""
        if self.axis.stacked:
            self.value_loss.write_back()
            self.guide_loss.write_back()

    def modules(self) -> dict:
        """What a checkpoint saves and a resumed run restores."""
        return {"value_loss": self.value_loss, "guide_loss": self.guide_loss, "value_optim": self.value_optim,
                "guide_optim": self.guide_optim, **self.axis.state_modules()}


def make_stage2(spec: RunSpec, seed_specs: Sequence[RunSpec], datas: Sequence[TensorDictBase],
                tsidms: Sequence[TSIDM], action_spec, axis: SeedAxis) -> Stage2:
    """Stage 2 of every seed of ``axis``, each built on its own stream as its own run (``seed_specs``) builds it."""
    stages = []
    for k, (seed_spec, data, tsidm) in enumerate(zip(seed_specs, datas, tsidms)):
        axis.start(k, seed_spec.seed)
        with axis.use(k):
            stages.append(make_seed_stage2(seed_spec, data, tsidm, action_spec))
    axis.seed_shared_stream(spec.seed + 1000)  # the same whether or not stage 1 ran in this process
    return Stage2(stages, axis, spec.precision_context(), spec.compile)


def fit_stage2(spec: RunSpec, stage2: Stage2, run: RunState, seed_runs: Sequence[RunState], folder: RunFolder,
               logger, evaluate: Callable[[int], dict]) -> int:
    """Algorithm 1, lines 7-8, from ``run``'s last checkpoint to ``policy.steps``, with the run's cadence
    (:func:`~torchrl_tels.run.loop.train_loop`): each seed's losses into its ``seed_runs`` history and the
    logger, ``evaluate(step)`` every ``eval.interval`` steps, checkpoints into ``folder``. Returns the step it
    started from."""
    axis, start = stage2.axis, 0
    if run.resumes("policy"):
        run.restore(**stage2.modules())
        start = run.step

    def log(step: int, losses) -> None:
        for k, seed_run in enumerate(seed_runs):
            scalars = {f"{name}/{key}": axis.of(value, k).item()
                       for name, out in zip(("value", "guide"), losses) for key, value in out.items()}
            for key, value in scalars.items():
                seed_run.policy_history.setdefault(key, []).append((step, value))
            logger.log_scalars({axis.prefix(k) + key: value for key, value in scalars.items()}, step)

    def checkpoint(step: int) -> None:
        run.step = step
        run.save(folder.state_path, **{name: module.state_dict() for name, module in stage2.modules().items()})

    with run.time("policy_s"):
        train_loop(lambda step: stage2.update(stage2.sample(), step), start=start, total=spec.policy.steps,
                   cadence=Cadence(spec.logger.log_interval, spec.checkpoint.interval, spec.eval.interval),
                   desc="stage 2: value + guide" + (f", {len(axis)} seeds" if axis.stacked else ""),
                   check_finite=stage2.check_finite, log=log, evaluate=evaluate, checkpoint=checkpoint)
    stage2.write_back()
    return start
