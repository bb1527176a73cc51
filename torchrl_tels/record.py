"""Run logging through TorchRL loggers: CSV always, wandb when it works."""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Mapping

from torchrl.record.loggers import CSVLogger

__all__ = ["RunLogger"]

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
