"""A T-symmetry consistency monitor: how far each transition is from what a trained TS-IDM accepts."""
from __future__ import annotations

import copy
import math
import os
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key

from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

from torchrl_tels.checkpoint import atomic_save, load_checkpoint
from torchrl_tels.errors import MonitorError
from torchrl_tels.modules.tsidm import squared_norm, TSIDM

__all__ = ["SCORE_TERMS", "TSymConsistencyMonitor"]

TSYM_KEY = "tsym_inconsistency"
DYNAMICS_KEY = "dynamics_residual"
ACTION_KEY = "action_residual"
SCORE_KEY = "ood_score"
FLAG_KEY = "ood"
#: The per-transition scores the monitor writes; any of them can be its ``ood_score``.
SCORE_TERMS = (TSYM_KEY, DYNAMICS_KEY, ACTION_KEY)


class TSymConsistencyMonitor(Transform):
    r"""Scores each transition :math:`(s, a, s')` by its disagreement with a frozen TS-IDM.

    With :math:`z_s = \phi_s(s)`, :math:`z_{s'} = \phi_s(s')` (states normalized
    as the TS-IDM was trained) and the latent action the TS-IDM infers from the
    two states, :math:`z_a = h_{inv}(z_s, z_{s'})`, the monitor writes

    * ``tsym_inconsistency``, Eq. (6) at :math:`(z_s, z_a)`:
      :math:`\|h_{fwd}(z_s, z_a) + h_{rvs}(z_s + h_{fwd}(z_s, z_a), z_a)\|_2^2`
      (:meth:`TSIDM.tsym_consistency <torchrl_tels.modules.TSIDM.tsym_consistency>`).
      The paper (§3.1, below Eq. 6) proposes this very value as an evaluation
      metric: a large one marks a latent transition that does not follow the
      learned dynamics, "a problematic or non-generalizable sample";
    * ``dynamics_residual``: :math:`\|z_s + h_{fwd}(z_s, z_a) - z_{s'}\|_2^2`, how far
      the latent ODE step misses the observed next latent (the relation
      :math:`z_{s'} = z_s + \dot z_s` stated below Eq. 6);
    * ``action_residual``: :math:`\|\psi_a(z_a) - a\|_2^2`, the action term of
      Eq. (3): the action the TS-IDM reads off :math:`(s, s')` against the one
      taken. It is the only score that uses :math:`a`; the other two see the
      action only through the state change it caused;
    * ``ood_score``: one of the three, chosen by ``score`` (default: the
      T-symmetry inconsistency, the paper's metric);
    * ``ood``: ``ood_score > threshold``, a boolean.

    Norms are sums of squares over the vector (``dim_reduction="sum"``, as the
    paper writes them) or means (``"mean"``), as in the TS-IDM's training.

    **Calibration.** :meth:`calibrate` sets ``threshold`` to the ``quantile`` of
    ``ood_score`` over the training transitions, so a fraction
    :math:`1 - q` of the training data is flagged. Both are buffers, saved in
    :meth:`state_dict` and by :meth:`save`. Asking an uncalibrated monitor for
    the flag raises a :class:`~torchrl_tels.errors.MonitorError`; build it with
    ``flag=False`` to record scores only.

    **Where it works.** Like
    :class:`~torchrl_tels.envs.TSIDMEncoderTransform`:

    * in a :class:`~torchrl.envs.TransformedEnv`: a transition is complete only
      after the step, so :meth:`_step` scores (root observation, root action,
      next observation) and writes the entries under ``"next"``, beside the
      reward; a reset writes zeros and ``False``. The entries are in the
      observation spec with shape ``(*batch, 1)``, and the env's observation and
      action sizes are checked against the TS-IDM's when the specs are built.
      The monitor reads the raw observation: put it before any transform that
      removes it;
    * on replay-buffer samples (``rb.append_transform(monitor)``) and on
      any tensordict of transitions (``monitor(td)``): root ``observation`` and
      ``action`` with ``("next", "observation")``; the scores go under ``"next"``;
    * at write time in a buffer (``rb.append_transform(monitor, invert=True)``).

    Bad input is refused with a :class:`~torchrl_tels.errors.MonitorError`
    naming it: an observation or action whose size differs from the TS-IDM's,
    or a NaN/inf in any of them.

    Args:
        tsidm (TSIDM, str or path-like): a trained TS-IDM or the path of a file
            written by :meth:`TSIDM.save <torchrl_tels.modules.TSIDM.save>`. A
            module is copied before being frozen. To load a saved monitor, use
            :meth:`load`.

    Keyword Args:
        score (str): which of :data:`SCORE_TERMS` is the ``ood_score``.
            Defaults to ``"tsym_inconsistency"``.
        flag (bool): write the ``ood`` flag (needs a calibrated monitor).
            Defaults to ``True``.
        dim_reduction (str): ``"sum"`` or ``"mean"`` over vector entries.
        observation_key, action_key (NestedKey): where the transition is read.
        observation_dim, action_dim (int, optional): sizes the TS-IDM must
            have; a mismatch is refused.
        threshold, quantile (float, optional): a calibration made before.

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from torchrl_tels.data import load_dataset
        >>> from torchrl_tels.envs import TSymConsistencyMonitor
        >>> monitor = TSymConsistencyMonitor("runs/a/tsidm.pt")
        >>> monitor.calibrate(load_dataset("hopper-medium-v2-10k"), quantile=0.99)
        >>> monitor.save("runs/a/monitor.pt")
        >>> env = TransformedEnv(GymEnv("Hopper-v4"), TSymConsistencyMonitor.load("runs/a/monitor.pt"))
        >>> rollout = env.rollout(100)
        >>> rollout["next", "ood_score"].shape, rollout["next", "ood"].float().mean()
    """

    invertible = False
    CHECKPOINT_FORMAT = "torchrl_tels.monitor/v1"

    def __init__(
        self,
        tsidm: TSIDM | str | os.PathLike,
        *,
        score: str = TSYM_KEY,
        flag: bool = True,
        dim_reduction: str = "sum",
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        observation_dim: int | None = None,
        action_dim: int | None = None,
        threshold: float | None = None,
        quantile: float | None = None,
    ) -> None:
        if isinstance(tsidm, (str, os.PathLike)):
            tsidm = TSIDM.load(tsidm, observation_dim=observation_dim, action_dim=action_dim)
        elif isinstance(tsidm, TSIDM):
            for name, expected in (("observation_dim", observation_dim), ("action_dim", action_dim)):
                if expected is not None and getattr(tsidm, name) != int(expected):
                    raise MonitorError(f"{type(self).__name__}: the TS-IDM has {name}={getattr(tsidm, name)}, "
                                       f"but {name}={expected} was requested: it was trained for another task.")
            tsidm = copy.deepcopy(tsidm)
        else:
            raise TypeError(f"{type(self).__name__} expects a TSIDM or the path of a saved TS-IDM, "
                            f"got {type(tsidm).__name__}.")
        if score not in SCORE_TERMS:
            raise MonitorError(f"{type(self).__name__}: score must be one of {SCORE_TERMS}, got {score!r}.")
        squared_norm(torch.zeros(1), dim_reduction)  # refuses an unknown reduction now, not at the first step
        observation_key, action_key = unravel_key(observation_key), unravel_key(action_key)
        out_keys = [*SCORE_TERMS, SCORE_KEY] + ([FLAG_KEY] if flag else [])
        super().__init__(in_keys=[observation_key, action_key], out_keys=out_keys)
        self.observation_key, self.action_key = observation_key, action_key
        tsidm.requires_grad_(False)
        self.tsidm = tsidm.eval()
        self.score_key = score
        self.flag = bool(flag)
        self.dim_reduction = dim_reduction
        self.register_buffer("threshold", torch.tensor(math.nan))
        self.register_buffer("quantile", torch.tensor(math.nan, dtype=torch.float64))
        if threshold is not None:
            self._set_calibration(threshold, math.nan if quantile is None else quantile)

    # ------------------------------------------------------------------ props
    @property
    def observation_dim(self) -> int:
        return self.tsidm.observation_dim

    @property
    def action_dim(self) -> int:
        return self.tsidm.action_dim

    @property
    def calibrated(self) -> bool:
        return bool(torch.isfinite(self.threshold))

    @property
    def _dtype(self) -> torch.dtype:
        return self.tsidm.obs_loc.dtype

    def train(self, mode: bool = True) -> "TSymConsistencyMonitor":
        # The TS-IDM is frozen: h_inv's dropout must stay off whatever the parent does.
        super().train(mode)
        self.tsidm.eval()
        return self

    # ----------------------------------------------------------------- scores
    def _check(self, name: str, value: torch.Tensor, size: int) -> None:
        if value.shape[-1:] != (size,):
            raise MonitorError(f"{type(self).__name__}: {name} has shape {tuple(value.shape)}, but the TS-IDM "
                               f"was trained on {name}s of size {size} (last dimension): another task's data?")
        if not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).reshape(-1, size).any(-1).sum())
            raise MonitorError(f"{type(self).__name__}: {name} holds NaN or inf in {bad} transition(s); "
                               "the scores of such a transition are meaningless.")

    def scores(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        *,
        check: bool = True,
    ) -> dict[str, torch.Tensor]:
        """The per-transition scores (shape ``observation.shape[:-1]``): every :data:`SCORE_TERMS` and ``ood_score``.

        ``check=False`` skips the size and finiteness checks (for tracing with :func:`torch.export.export`,
        where a data-dependent check cannot be compiled).
        """
        if check:
            self._check("observation", observation, self.observation_dim)
            self._check("next observation", next_observation, self.observation_dim)
            self._check("action", action, self.action_dim)
        tsidm, reduction = self.tsidm, self.dim_reduction
        with torch.no_grad():
            z = tsidm.encode_state(observation)
            z_next = tsidm.encode_state(next_observation)
            z_a = tsidm.infer_latent_action(z, z_next)
            out = {
                TSYM_KEY: tsidm.tsym_consistency(z, z_a, reduction),  # Eq. (6)
                DYNAMICS_KEY: squared_norm(z + tsidm.latent_forward(z, z_a) - z_next, reduction),
                ACTION_KEY: squared_norm(tsidm.decode_action(z_a) - action.to(self._dtype), reduction),  # Eq. (3)
            }
        out[SCORE_KEY] = out[self.score_key]
        return out

    def is_ood(self, score: torch.Tensor, *, check: bool = True) -> torch.Tensor:
        """``score > threshold``; refused on an uncalibrated monitor (``check=False``: for tracing, no check)."""
        if check and not self.calibrated:
            raise MonitorError(f"{type(self).__name__} is not calibrated: call monitor.calibrate(training_data) "
                               "before asking for the 'ood' flag, or build it with flag=False to record scores only.")
        return score > self.threshold

    # ------------------------------------------------------------ calibration
    def _set_calibration(self, threshold: float, quantile: float) -> None:
        # New tensors rather than in-place copies: a clone() shares its buffers with the original.
        self.threshold = torch.tensor(float(threshold), dtype=self._dtype)
        self.quantile = torch.tensor(float(quantile), dtype=torch.float64)

    @torch.no_grad()
    def calibrate(self, data: TensorDictBase, quantile: float = 0.99, batch_size: int = 65536) -> float:
        """Sets ``threshold`` to the ``quantile`` of ``ood_score`` over ``data`` (the training transitions).

        ``data`` holds ``observation``, ``action`` and ``("next", "observation")``; a fraction
        ``1 - quantile`` of it is then flagged. Returns the threshold.
        """
        if not 0.0 < float(quantile) < 1.0:
            raise MonitorError(f"{type(self).__name__}.calibrate: quantile must lie in (0, 1), got {quantile}.")
        scores = self._data_scores(data, batch_size)[SCORE_KEY].reshape(-1)
        if scores.numel() == 0:
            raise MonitorError(f"{type(self).__name__}.calibrate: the data holds no transitions.")
        threshold = torch.quantile(scores.double(), float(quantile)).item()
        self._set_calibration(threshold, quantile)
        return threshold

    def _data_scores(self, data: TensorDictBase, batch_size: int = 65536) -> dict[str, torch.Tensor]:
        keys = (self.observation_key, self.action_key, ("next", self.observation_key))
        missing = [key for key in keys if unravel_key(key) not in data.keys(True)]
        if missing:
            raise MonitorError(f"{type(self).__name__}: the data has no {missing} "
                               f"(keys: {sorted(map(str, data.keys(True, True)))}).")
        data = data.reshape(-1)
        chunks = [self.scores(*(chunk.get(key) for key in keys)) for chunk in data.split(batch_size)]
        return {name: torch.cat([chunk[name] for chunk in chunks]) for name in chunks[0]}

    # ----------------------------------------------------------- tensordicts
    def _write(self, next_tensordict: TensorDictBase, scores: dict[str, torch.Tensor]) -> TensorDictBase:
        for name, value in scores.items():
            next_tensordict.set(name, value.unsqueeze(-1))
        if self.flag:
            next_tensordict.set(FLAG_KEY, self.is_ood(scores[SCORE_KEY]).unsqueeze(-1))
        return next_tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # The transition (s, a, s') is complete only now: s and a at the root, s' in the step's output.
        scores = self.scores(tensordict.get(self.observation_key), tensordict.get(self.action_key),
                             next_tensordict.get(self.observation_key))
        return self._write(next_tensordict, scores)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # No transition has happened yet: zeros, and no flag.
        zeros = torch.zeros(tensordict_reset.batch_size, dtype=self._dtype, device=tensordict_reset.device)
        return self._write(tensordict_reset, {name: zeros for name in (*SCORE_TERMS, SCORE_KEY)})

    def _score_transitions(self, tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = tensordict.get("next", None)
        if next_tensordict is None:
            raise MonitorError(f"{type(self).__name__}: the tensordict has no 'next' entry; the monitor scores "
                               "transitions (observation, action, ('next', observation)).")
        scores = self._data_scores(tensordict.select(self.observation_key, self.action_key,
                                                     ("next", self.observation_key)))
        shape = tensordict.batch_size
        self._write(next_tensordict, {name: value.reshape(shape) for name, value in scores.items()})
        return tensordict

    def _call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Write path of rb.append_transform(monitor, invert=True): whole transitions. In an env, _step runs instead.
        return self._score_transitions(tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Replay-buffer samples and direct calls.
        return self._score_transitions(tensordict)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    # ----------------------------------------------------------------- specs
    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise TypeError(f"{type(self).__name__} expects a Composite observation spec, "
                            f"got {type(observation_spec).__name__}.")
        if self.observation_key not in observation_spec.keys(True, True):
            raise MonitorError(f"{type(self).__name__}: the environment has no observation {self.observation_key!r} "
                               f"(observation keys: {sorted(map(str, observation_spec.keys(True, True)))}).")
        in_spec = observation_spec[self.observation_key]
        if in_spec.shape[-1:] != (self.observation_dim,):
            raise MonitorError(f"{type(self).__name__}: the environment's observation {self.observation_key!r} has "
                               f"spec shape {tuple(in_spec.shape)}, but the TS-IDM was trained on observations of "
                               f"size {self.observation_dim}: it was trained for another environment.")
        shape = observation_spec.shape + (1,)
        for name in (*SCORE_TERMS, SCORE_KEY):
            observation_spec[name] = Unbounded(shape=shape, dtype=self._dtype, device=observation_spec.device)
        if self.flag:
            observation_spec[FLAG_KEY] = Categorical(2, shape=shape, dtype=torch.bool, device=observation_spec.device)
        return observation_spec

    def transform_action_spec(self, action_spec: TensorSpec) -> TensorSpec:
        spec = action_spec[self.action_key] if isinstance(action_spec, Composite) else action_spec
        if spec.shape[-1:] != (self.action_dim,):
            raise MonitorError(f"{type(self).__name__}: the environment's action {self.action_key!r} has spec "
                               f"shape {tuple(spec.shape)}, but the TS-IDM was trained on actions of size "
                               f"{self.action_dim}: it was trained for another environment.")
        return action_spec

    # ------------------------------------------------------------- save/load
    def save(self, path: str | os.PathLike, metadata: dict[str, Any] | None = None) -> None:
        """Writes the TS-IDM (config and weights), the calibration and the options atomically."""
        atomic_save(
            {
                "format": self.CHECKPOINT_FORMAT,
                "tsidm": self.tsidm.checkpoint_payload(),
                "threshold": float(self.threshold),
                "quantile": float(self.quantile),
                "score": self.score_key,
                "dim_reduction": self.dim_reduction,
                "metadata": dict(metadata or {}),
            },
            path,
        )

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        *,
        observation_dim: int | None = None,
        action_dim: int | None = None,
        **kwargs,
    ) -> "TSymConsistencyMonitor":
        """Rebuilds a monitor written by :meth:`save`; ``observation_dim``/``action_dim`` refuse another task's.

        ``kwargs`` (``flag``, ``observation_key``, ``action_key``) go to the constructor.
        """
        payload = load_checkpoint(path, cls.CHECKPOINT_FORMAT)
        tsidm = TSIDM.from_payload(payload["tsidm"], path, observation_dim=observation_dim, action_dim=action_dim)
        threshold = payload["threshold"]
        monitor = cls(tsidm, score=payload["score"], dim_reduction=payload["dim_reduction"],
                      threshold=None if math.isnan(threshold) else threshold, quantile=payload["quantile"], **kwargs)
        monitor.metadata = payload.get("metadata", {})
        return monitor

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(score={self.score_key!r}, threshold={float(self.threshold):.4g}, "
                f"quantile={float(self.quantile):.4g}, observation_dim={self.observation_dim}, "
                f"action_dim={self.action_dim})")
