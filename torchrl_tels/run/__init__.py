"""One run of Algorithm 1, piece by piece, for ``recipes/tels_offline.py`` and the scripts that rebuild part of a
run: its data (:mod:`~torchrl_tels.run.data`), its resumable state (:class:`RunState`), stage 1
(:mod:`~torchrl_tels.run.stage1`), stage 2 (:mod:`~torchrl_tels.run.stage2`), the one training loop both run in
(:func:`train_loop`) and evaluation (:mod:`~torchrl_tels.run.evaluation`). Every stage trains the seeds of a
:class:`~torchrl_tels.seeds.SeedAxis`: one seed as a plain run, or several stacked in one process. Each piece reads
the typed :class:`~torchrl_tels.config.RunSpec`, never a hydra config.
"""
from torchrl_tels.run.data import check_same_stage1_length, diagnostic_indices, make_data, print_plan, tsidm_steps
from torchrl_tels.run.evaluation import after_training_diagnostics, evaluate, evaluation_scalars
from torchrl_tels.run.loop import Cadence, make_train_step, train_loop
from torchrl_tels.run.stage1 import fit_tsidm, load_pretrained_tsidm, make_stage1, make_tsidm, make_tsidm_loss
from torchrl_tels.run.stage2 import fit_stage2, make_seed_stage2, make_stage2, SeedStage2, Stage2
from torchrl_tels.run.state import RunState, start_run

__all__ = [
    "Cadence",
    "RunState",
    "SeedStage2",
    "Stage2",
    "after_training_diagnostics",
    "check_same_stage1_length",
    "diagnostic_indices",
    "evaluate",
    "evaluation_scalars",
    "fit_stage2",
    "fit_tsidm",
    "load_pretrained_tsidm",
    "make_data",
    "make_seed_stage2",
    "make_stage1",
    "make_stage2",
    "make_train_step",
    "make_tsidm",
    "make_tsidm_loss",
    "print_plan",
    "start_run",
    "train_loop",
    "tsidm_steps",
]
