"""A deployment monitor: how far each transition, and each stretch of an episode, is from the data."""
from __future__ import annotations

import copy
import math
import os
from collections.abc import Sequence
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key

from torchrl.data import Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

from torchrl_tels.checkpoint import atomic_save, CheckpointError, load_checkpoint
from torchrl_tels.data.subsets import trajectory_ids
from torchrl_tels.errors import MonitorError
from torchrl_tels.modules.detectors import DynamicsEnsemble, fit_ensembles, NearestStateDistance
from torchrl_tels.modules.tsidm import squared_norm, TSIDM

__all__ = ["DEFAULT_COMBINATION", "DeploymentMonitor", "SCORE_TERMS", "conformal_threshold", "running_mean",
           "steps_into_trajectory"]

TSYM_KEY = "tsym_inconsistency"
DYNAMICS_KEY = "dynamics_residual"
ACTION_KEY = "action_residual"
MODEL_KEY = "model_residual"
DISAGREEMENT_KEY = "model_disagreement"
NEAREST_KEY = "nearest_state"
#: The scores read off the TS-IDM.
TSIDM_TERMS = (TSYM_KEY, DYNAMICS_KEY, ACTION_KEY)
#: Every per-transition score the monitor can write; each needs its detector.
SCORE_TERMS = (*TSIDM_TERMS, MODEL_KEY, DISAGREEMENT_KEY, NEAREST_KEY)
#: The terms the default ``ood_score`` averages: the two that lead the benchmark (BENCHMARKS.md, "Deployment monitor").
DEFAULT_COMBINATION = (MODEL_KEY, NEAREST_KEY)
COMBINED = "combined"
SCORE_KEY = "ood_score"
FLAG_KEY = "ood"
WINDOW_KEY = "ood_window"
ALARM_KEY = "ood_alarm"
RECENT_KEY = "ood_recent"
COUNT_KEY = "ood_count"
_TINY = 1e-12  # keeps log() finite at a score of exactly 0


def _check_quantiles(name: str, quantile: float, window_quantile: float) -> None:
    for label, q in (("quantile", quantile), ("window_quantile", window_quantile)):
        if not 0.0 < float(q) < 1.0:
            raise MonitorError(f"{name}: {label} must lie in (0, 1), got {q}.")


def conformal_threshold(scores: torch.Tensor, quantile: float) -> float:
    r"""The split-conformal threshold: the :math:`\lceil (n+1) q \rceil`-th smallest of ``n`` calibration scores.

    A new score exchangeable with the calibration scores exceeds it with probability at most
    :math:`1 - q` (and at least :math:`1 - q - 1/(n+1)` without ties). When :math:`(n+1)q > n` no
    calibration score is high enough for that bound, and the largest is returned. Transitions of one
    trajectory are not exchangeable with each other, so for a monitor the bound is an estimate whose
    quality depends on the number of calibration trajectories (``benchmarks.monitor_benchmark`` measures it).
    """
    if not 0.0 < float(quantile) < 1.0:
        raise MonitorError(f"conformal_threshold: the quantile must lie in (0, 1), got {quantile}.")
    scores = scores.reshape(-1).double().sort().values
    rank = min(math.ceil((len(scores) + 1) * float(quantile)), len(scores))
    return float(scores[rank - 1])


def steps_into_trajectory(trajectory: torch.Tensor) -> torch.Tensor:
    """``0, 1, 2, ...`` along the last dimension, restarting wherever the trajectory id changes."""
    time = torch.arange(trajectory.shape[-1], device=trajectory.device).expand_as(trajectory)
    start = torch.ones_like(trajectory, dtype=torch.bool)
    start[..., 1:] = trajectory[..., 1:] != trajectory[..., :-1]
    return time - torch.cummax(torch.where(start, time, torch.zeros_like(time)), -1).values


def running_mean(scores: torch.Tensor, window: int, trajectory: torch.Tensor | None = None) -> torch.Tensor:
    """The mean of each step's score and the ``window - 1`` steps before it in the same trajectory.

    ``scores`` has time as its last dimension; ``trajectory`` (the same shape, optional) numbers the
    trajectory of each step, so a window never reaches into the previous trajectory. Early in a
    trajectory the mean is over the steps so far, as the monitor computes it online.
    """
    scores = scores.double()
    if trajectory is None:
        trajectory = torch.zeros(scores.shape, dtype=torch.long, device=scores.device)
    trajectory = trajectory.to(scores.device)
    time = torch.arange(scores.shape[-1], device=scores.device).expand_as(scores)
    first = time - steps_into_trajectory(trajectory)  # the first step of each step's trajectory
    lower = torch.maximum(first, time - window + 1)
    cumulative = torch.cat([torch.zeros_like(scores[..., :1]), scores.cumsum(-1)], -1)
    total = cumulative[..., 1:] - cumulative.gather(-1, lower)
    return total / (time - lower + 1)


class DeploymentMonitor(Transform):
    r"""Scores each transition :math:`(s, a, s')` by how far it is from the data, and raises alarms over a window.

    **Detectors.** Each given component adds its scores (per transition, larger = farther):

    * a trained :class:`~torchrl_tels.modules.TSIDM` (``tsidm``), with :math:`z_s = \phi_s(s)`,
      :math:`z_{s'} = \phi_s(s')` and :math:`z_a = h_{inv}(z_s, z_{s'})`:

      - ``tsym_inconsistency``, Eq. (6) at :math:`(z_s, z_a)`, the value the paper (§3.1, below Eq. 6)
        proposes for spotting "a problematic or non-generalizable sample";
      - ``dynamics_residual``: :math:`\|z_s + h_{fwd}(z_s, z_a) - z_{s'}\|_2^2`;
      - ``action_residual``: :math:`\|\psi_a(z_a) - a\|_2^2`, the action term of Eq. (3);

    * a :class:`~torchrl_tels.modules.DynamicsEnsemble` (``dynamics``): ``model_residual``, the
      miss of the one-step models' mean prediction, and ``model_disagreement``, their spread;
    * a :class:`~torchrl_tels.modules.NearestStateDistance` (``states``): ``nearest_state``, the
      distance from :math:`s'` to the nearest data state.

    **The monitor's score.** Each term :math:`r_j` is put on a common scale by its calibration
    data, :math:`u_j = (\log r_j - m_j) / \sigma_j`, and ``ood_score`` is :math:`u` of the term named
    by ``score`` or, with ``score="combined"`` (the default), the mean of :math:`u_j` over
    ``combine``. ``ood`` is ``ood_score > threshold``.

    **The window.** In an environment the monitor keeps the last ``window`` scores of the episode
    (``ood_recent``, ``ood_count``, carried from step to step like any observation) and writes
    their mean, ``ood_window``, and ``ood_alarm = ood_window > window_threshold``. A changed plant
    or a drift moves each transition little; the mean over many moves further from its calibration
    spread. :func:`running_mean` computes the same statistic offline.

    **Calibration.** :meth:`calibrate` takes in-distribution trajectories *that the detectors were
    not fitted to* (a held-out split: :func:`~torchrl_tels.data.split_trajectories`, or
    :meth:`fit`, which does both), and sets :math:`m_j, \sigma_j`, then ``threshold`` and
    ``window_threshold`` by split-conformal calibration (:func:`conformal_threshold`) at
    ``quantile`` and ``window_quantile``. A detector scores the data it was fitted to lower than new
    data, so thresholds set on its training data alarm far more often than their nominal rate.

    **Where it works.** As a :class:`~torchrl.envs.Transform`:

    * in a :class:`~torchrl.envs.TransformedEnv`: :meth:`_step` scores (root observation, root
      action, next observation) and writes every entry under ``"next"``; a reset writes zeros and
      ``False``. Observation and action sizes are checked when the specs are built. The monitor
      must see the raw observation at both ends of a transition: put it first in the chain, before
      any transform that changes or removes the observation;
    * on replay-buffer samples (``rb.append_transform(monitor)``) and any tensordict of transitions
      (``monitor(td)``): the per-transition entries (not the window) go under ``"next"``;
    * at write time in a buffer (``rb.append_transform(monitor, invert=True)``).

    A size that differs from the detectors', a NaN or inf in the stream, or a tensordict without
    the transition's keys is refused with one :class:`~torchrl_tels.errors.MonitorError` naming it.

    Keyword Args:
        tsidm (TSIDM, str or path-like, optional): a trained TS-IDM (copied, then frozen) or its file.
        dynamics (DynamicsEnsemble, optional): a fitted one-step ensemble (copied, frozen).
        states (NearestStateDistance, optional): the data's states (copied).
        score (str): ``"combined"`` or one of the available :data:`SCORE_TERMS`. Defaults to ``"combined"``.
        combine (sequence of str, optional): the terms the combined score averages. Defaults to the
            available terms of :data:`DEFAULT_COMBINATION`, or every available term if none is.
        window (int): steps the windowed mean covers. Defaults to 100.
        flag (bool): write ``ood`` and ``ood_alarm`` (they need a calibrated monitor). Defaults to True.
        dim_reduction (str): ``"sum"`` or ``"mean"`` over vector entries, for the TS-IDM terms.
        observation_key, action_key (NestedKey): where the transition is read.
        observation_dim, action_dim (int, optional): sizes the detectors must have.

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from torchrl_tels.data import load_dataset, split_trajectories
        >>> from torchrl_tels.envs import DeploymentMonitor
        >>> train, held_out = split_trajectories(load_dataset("hopper-medium-v2-10k"), 0.8, seed=0)
        >>> monitor = DeploymentMonitor.fit(train, held_out)
        >>> monitor.save("monitor.pt")
        >>> env = TransformedEnv(GymEnv("Hopper-v4"), DeploymentMonitor.load("monitor.pt"))
        >>> rollout = env.rollout(300)
        >>> rollout["next", "ood_window"].shape, rollout["next", "ood_alarm"].any()
    """

    invertible = False
    CHECKPOINT_FORMAT = "torchrl_tels.monitor/v2"

    def __init__(
        self,
        *,
        tsidm: TSIDM | str | os.PathLike | None = None,
        dynamics: DynamicsEnsemble | None = None,
        states: NearestStateDistance | None = None,
        score: str = COMBINED,
        combine: Sequence[str] | None = None,
        window: int = 100,
        flag: bool = True,
        dim_reduction: str = "sum",
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        observation_dim: int | None = None,
        action_dim: int | None = None,
    ) -> None:
        name = type(self).__name__
        if isinstance(tsidm, (str, os.PathLike)):
            tsidm = TSIDM.load(tsidm, observation_dim=observation_dim, action_dim=action_dim)
        for label, module, kind in (("tsidm", tsidm, TSIDM), ("dynamics", dynamics, DynamicsEnsemble),
                                    ("states", states, NearestStateDistance)):
            if module is not None and not isinstance(module, kind):
                raise TypeError(f"{name}: {label} must be a {kind.__name__}, got {type(module).__name__}.")
        if tsidm is None and dynamics is None and states is None:
            raise MonitorError(f"{name} needs at least one detector: a tsidm, a dynamics ensemble or the states.")
        sizes = {"observation_dim": {}, "action_dim": {}}
        for label, module in (("tsidm", tsidm), ("dynamics", dynamics)):
            if module is not None:
                sizes["observation_dim"][label] = module.observation_dim
                sizes["action_dim"][label] = module.action_dim
        if states is not None:
            sizes["observation_dim"]["states"] = states.bank.shape[-1]
        for size, found in sizes.items():
            requested = {"observation_dim": observation_dim, "action_dim": action_dim}[size]
            if requested is not None:
                found = {**found, "requested": int(requested)}
            if len(set(found.values())) > 1:
                raise MonitorError(f"{name}: the detectors disagree on {size} ({found}): they were made for "
                                   "different tasks.")
        self._observation_dim = next(iter(sizes["observation_dim"].values()))
        self._action_dim = next(iter(sizes["action_dim"].values()), None if action_dim is None else int(action_dim))

        terms = (TSIDM_TERMS if tsidm is not None else ()) + ((MODEL_KEY, DISAGREEMENT_KEY) if dynamics is not None else ()) \
            + ((NEAREST_KEY,) if states is not None else ())
        if combine is None:
            combine = tuple(t for t in DEFAULT_COMBINATION if t in terms) or terms
        combine = tuple(combine)
        unknown = [t for t in combine if t not in terms] + ([score] if score not in (*terms, COMBINED) else [])
        if unknown or not combine:
            raise MonitorError(f"{name}: score must be 'combined' or one of the available terms {terms}, and "
                               f"combine a non-empty list of them; got score={score!r}, combine={list(combine)}.")
        if int(window) < 1:
            raise MonitorError(f"{name}: window must be at least 1 step, got {window}.")
        squared_norm(torch.zeros(1), dim_reduction)  # refuses an unknown reduction now, not at the first step
        observation_key, action_key = unravel_key(observation_key), unravel_key(action_key)
        self.terms, self.score_key, self.combine = terms, score, combine
        self.window, self.flag = int(window), bool(flag)
        out_keys = [*terms, SCORE_KEY, WINDOW_KEY, RECENT_KEY, COUNT_KEY] + ([FLAG_KEY, ALARM_KEY] if flag else [])
        super().__init__(in_keys=[observation_key, action_key], out_keys=out_keys)
        self.observation_key, self.action_key = observation_key, action_key
        self.dim_reduction = dim_reduction
        self.tsidm = self._frozen(tsidm)
        self.dynamics = self._frozen(dynamics)
        self.states = self._frozen(states)
        self.register_buffer("term_loc", torch.zeros(len(terms)))
        self.register_buffer("term_scale", torch.ones(len(terms)))
        for buffer in ("threshold", "window_threshold"):
            self.register_buffer(buffer, torch.tensor(math.nan))
        for buffer in ("quantile", "window_quantile"):
            self.register_buffer(buffer, torch.tensor(math.nan, dtype=torch.float64))
        self.metadata: dict[str, Any] = {}

    @staticmethod
    def _frozen(module):
        if module is None:
            return None
        module = copy.deepcopy(module)
        module.requires_grad_(False)
        return module.eval()

    # ------------------------------------------------------------------ props
    @property
    def observation_dim(self) -> int:
        return self._observation_dim

    @property
    def action_dim(self) -> int | None:
        return self._action_dim

    @property
    def calibrated(self) -> bool:
        return bool(torch.isfinite(self.threshold)) and bool(torch.isfinite(self.window_threshold))

    def train(self, mode: bool = True) -> "DeploymentMonitor":
        # The detectors are frozen: h_inv's dropout must stay off whatever the parent does.
        super().train(mode)
        for module in (self.tsidm, self.dynamics, self.states):
            if module is not None:
                module.eval()
        return self

    # ----------------------------------------------------------------- scores
    def _check(self, label: str, value: torch.Tensor, size: int | None) -> None:
        if size is not None and value.shape[-1:] != (size,):
            raise MonitorError(f"{type(self).__name__}: {label} has shape {tuple(value.shape)}, but the monitor "
                               f"was fitted to {label}s of size {size} (last dimension): another task's data?")
        if not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).reshape(-1, value.shape[-1]).any(-1).sum())
            raise MonitorError(f"{type(self).__name__}: {label} holds NaN or inf in {bad} transition(s); "
                               "the scores of such a transition are meaningless.")

    def raw_scores(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor,
                   *, check: bool = True) -> dict[str, torch.Tensor]:
        """Every available term (see :data:`SCORE_TERMS`), shape ``observation.shape[:-1]``, in its own units.

        ``check=False`` skips the size and finiteness checks (for :func:`torch.export.export`, which
        cannot trace a data-dependent check).
        """
        if check:
            self._check("observation", observation, self.observation_dim)
            self._check("next observation", next_observation, self.observation_dim)
            self._check("action", action, self.action_dim)
        out = {}
        with torch.no_grad():
            if self.tsidm is not None:
                tsidm, reduction = self.tsidm, self.dim_reduction
                z = tsidm.encode_state(observation)
                z_next = tsidm.encode_state(next_observation)
                z_a = tsidm.infer_latent_action(z, z_next)
                out[TSYM_KEY] = tsidm.tsym_consistency(z, z_a, reduction)  # Eq. (6)
                out[DYNAMICS_KEY] = squared_norm(z + tsidm.latent_forward(z, z_a) - z_next, reduction)
                out[ACTION_KEY] = squared_norm(tsidm.decode_action(z_a) - action.to(z.dtype), reduction)  # Eq. (3)
            if self.dynamics is not None:
                out[MODEL_KEY], out[DISAGREEMENT_KEY] = self.dynamics.scores(observation, action, next_observation)
            if self.states is not None:
                out[NEAREST_KEY] = self.states(next_observation)
        return {term: out[term].float() for term in self.terms}

    def standardize(self, raw: dict[str, torch.Tensor]) -> torch.Tensor:
        """:math:`u_j = (\\log r_j - m_j) / \\sigma_j` of every term, stacked on a last dimension (in ``terms`` order)."""
        logs = torch.stack([raw[term].clamp_min(0.0).add(_TINY).log() for term in self.terms], -1)
        return (logs - self.term_loc) / self.term_scale

    def ood_score(self, standardized: torch.Tensor) -> torch.Tensor:
        """The monitor's score from :meth:`standardize`'s output: one term's, or the mean over ``combine``."""
        chosen = self.combine if self.score_key == COMBINED else (self.score_key,)
        index = [self.terms.index(term) for term in chosen]
        return standardized[..., index].mean(-1)

    def scores(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor,
               *, check: bool = True) -> dict[str, torch.Tensor]:
        """Every available term and ``ood_score``, shape ``observation.shape[:-1]``."""
        raw = self.raw_scores(observation, action, next_observation, check=check)
        return {**raw, SCORE_KEY: self.ood_score(self.standardize(raw))}

    def _require_calibration(self, what: str) -> None:
        if not self.calibrated:
            raise MonitorError(f"{type(self).__name__} is not calibrated: call monitor.calibrate(held_out_data) "
                               f"before asking for {what}, or build it with flag=False to record scores only.")

    def is_ood(self, score: torch.Tensor, *, check: bool = True) -> torch.Tensor:
        """``score > threshold``; refused on an uncalibrated monitor (``check=False``: no check, for tracing)."""
        if check:
            self._require_calibration("the 'ood' flag")
        return score > self.threshold

    def update_window(self, recent: torch.Tensor, count: torch.Tensor,
                      score: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of the windowed mean: (recent scores, steps so far capped at ``window``, new score)
        → (window mean, new recent, new count). ``recent`` has shape ``(*batch, window)``, oldest first,
        zeros where the episode has not reached; ``count`` has shape ``(*batch, 1)``."""
        recent = torch.cat([recent[..., 1:], score.unsqueeze(-1).to(recent.dtype)], -1)
        count = (count + 1).clamp_max(self.window)
        return recent.sum(-1) / count.squeeze(-1).to(recent.dtype), recent, count

    # ------------------------------------------------------------ calibration
    @torch.no_grad()
    def calibrate(self, data: TensorDictBase, quantile: float = 0.99, window_quantile: float = 0.999,
                  batch_size: int = 2048) -> dict[str, float]:
        """Sets the terms' scales, ``threshold`` and ``window_threshold`` from held-out trajectories.

        ``data`` holds ``observation``, ``action``, ``("next", "observation")`` and ``"episode"``,
        from trajectories the detectors were not fitted to. A new in-distribution transition is then
        flagged with probability at most ``1 - quantile``, and a step's windowed mean with at most
        ``1 - window_quantile`` (split-conformal calibration; see :func:`conformal_threshold`).
        Returns both thresholds.
        """
        name = f"{type(self).__name__}.calibrate"
        _check_quantiles(name, quantile, window_quantile)
        if "episode" not in data.keys():
            raise MonitorError(f"{name}: the data has no 'episode' entry, so its trajectories (which the windowed "
                               "mean runs along) cannot be told apart.")
        raw = self._data_scores(data, batch_size)
        return self._calibrate_scores(raw, trajectory_ids(data.reshape(-1)), quantile, window_quantile)

    def _calibrate_scores(self, raw: dict[str, torch.Tensor], trajectory: torch.Tensor, quantile: float,
                          window_quantile: float) -> dict[str, float]:
        if len(trajectory) < 2:
            raise MonitorError(f"{type(self).__name__}.calibrate: the data holds {len(trajectory)} transition(s); "
                               "it needs at least 2.")
        logs = torch.stack([raw[term].clamp_min(0.0).add(_TINY).log() for term in self.terms], -1).double()
        self.term_loc = logs.mean(0).float()
        self.term_scale = logs.std(0).clamp_min(1e-6).float()
        score = self.ood_score(self.standardize(raw))
        window = running_mean(score, self.window, trajectory)
        device = self.term_loc.device
        self.threshold = torch.tensor(conformal_threshold(score, quantile), device=device)
        self.window_threshold = torch.tensor(conformal_threshold(window, window_quantile), device=device)
        self.quantile = torch.tensor(float(quantile), dtype=torch.float64, device=device)
        self.window_quantile = torch.tensor(float(window_quantile), dtype=torch.float64, device=device)
        return {"threshold": float(self.threshold), "window_threshold": float(self.window_threshold)}

    @staticmethod
    def _check_options(name: str, calibration: TensorDictBase, quantile: float, window_quantile: float,
                       options: dict) -> None:
        """What would fail after the fits, checked before them."""
        _check_quantiles(name, quantile, window_quantile)
        if "episode" not in calibration.keys():
            raise MonitorError(f"{name}: the calibration data has no 'episode' entry, so its trajectories (which "
                               "the windowed mean runs along) cannot be told apart.")
        if int(options.get("window", 1)) < 1:
            raise MonitorError(f"{name}: window must be at least 1 step, got {options['window']}.")

    @staticmethod
    def _transitions(data: TensorDictBase, label: str, caller: str) -> tuple[torch.Tensor, ...]:
        keys = ("observation", "action", ("next", "observation"))
        missing = [key for key in keys if unravel_key(key) not in data.keys(True)]
        if missing:
            raise MonitorError(f"{caller}: the {label} data has no {missing}.")
        values = tuple(data.get(key).reshape(-1, data.get(key).shape[-1]).float() for key in keys)
        for key, value in zip(("observation", "action", "next observation"), values):
            if not torch.isfinite(value).all():
                raise MonitorError(f"{caller}: the {label} data's {key} holds NaN or inf.")
        return values

    @staticmethod
    def fit_detectors(data: TensorDictBase, *, members: int = 5, num_cells: Sequence[int] = (200, 200),
                      steps: int = 3000, max_states: int = 20000, seed: int = 0,
                      precision: str = "fp32") -> tuple[DynamicsEnsemble, NearestStateDistance]:
        """A :class:`DynamicsEnsemble` (trained in ``precision``) and a :class:`NearestStateDistance` fitted to
        ``data``'s transitions."""
        return DeploymentMonitor._fit_detector_sets([data], [seed], members=members, num_cells=num_cells,
                                                    steps=steps, max_states=max_states, precision=precision)[0]

    @staticmethod
    def _fit_detector_sets(datasets: Sequence[TensorDictBase], seeds: Sequence[int], *, members: int,
                           num_cells: Sequence[int], steps: int, max_states: int,
                           precision: str) -> list[tuple[DynamicsEnsemble, NearestStateDistance]]:
        """:meth:`fit_detectors` on each of ``datasets`` with its seed; the dynamics ensembles train at once
        (:func:`~torchrl_tels.modules.detectors.fit_ensembles`), each as it would alone."""
        transitions = [DeploymentMonitor._transitions(data, "train", "fit_detectors") for data in datasets]
        ensembles = []
        for (observation, action, _), seed in zip(transitions, seeds):
            with torch.random.fork_rng(devices=[]):  # seeded, and the caller's RNG stream left as it was
                torch.manual_seed(seed)
                ensembles.append(DynamicsEnsemble(observation.shape[-1], action.shape[-1], members=members,
                                                  num_cells=tuple(num_cells)))
        fit_ensembles(ensembles, transitions, seeds=seeds, steps=steps, precision=precision)
        return [(ensemble, NearestStateDistance(torch.cat([observation, next_observation]), max_states=max_states,
                                                seed=seed))
                for ensemble, (observation, _, next_observation), seed in zip(ensembles, transitions, seeds)]

    @classmethod
    def fit(cls, train: TensorDictBase, calibration: TensorDictBase, *, tsidm: TSIDM | None = None,
            members: int = 5, num_cells: Sequence[int] = (200, 200), steps: int = 3000, max_states: int = 20000,
            quantile: float = 0.99, window_quantile: float = 0.999, seed: int = 0, precision: str = "fp32",
            **kwargs) -> "DeploymentMonitor":
        """Split calibration: fits the detectors (:meth:`fit_detectors`) to ``train`` and calibrates on
        ``calibration``, held-out trajectories. ``tsidm`` adds the T-symmetry terms; its own training data
        must exclude ``calibration`` too. ``kwargs`` go to the constructor."""
        cls._check_options(f"{cls.__name__}.fit", calibration, quantile, window_quantile, kwargs)
        cls._transitions(calibration, "calibration", f"{cls.__name__}.fit")
        dynamics, states = cls.fit_detectors(train, members=members, num_cells=num_cells, steps=steps,
                                             max_states=max_states, seed=seed, precision=precision)
        monitor = cls(tsidm=tsidm, dynamics=dynamics, states=states, **kwargs)
        monitor.calibrate(calibration, quantile=quantile, window_quantile=window_quantile)
        monitor.metadata = {"calibration": "split", "train_transitions": int(train.numel()),
                            "calibration_transitions": int(calibration.numel()), "seed": seed}
        return monitor

    @classmethod
    def cross_fit(cls, data: TensorDictBase, *, folds: int = 5, members: int = 5,
                  num_cells: Sequence[int] = (200, 200), steps: int = 3000, max_states: int = 20000,
                  quantile: float = 0.99, window_quantile: float = 0.999, seed: int = 0, precision: str = "fp32",
                  **kwargs) -> "DeploymentMonitor":
        """Cross-fitted calibration: every trajectory of ``data`` calibrates, scored by detectors that never saw it.

        The trajectories are dealt into ``folds`` groups; for each, the detectors are fitted to the other
        groups and score it. The terms' scales and both thresholds come from these out-of-fold scores
        of the whole dataset, and the deployed detectors are then fitted to all of it. A detector fitted
        to more data scores new data no higher, so the thresholds err towards fewer alarms. It costs
        ``folds + 1`` fits, trained as one stacked ensemble (:func:`~torchrl_tels.modules.detectors.fit_ensembles`),
        and with few trajectories calibrates on all of them rather than a fifth.
        A TS-IDM is not refitted here, so the T-symmetry terms need :meth:`fit`.
        """
        name = f"{cls.__name__}.cross_fit"
        if int(folds) < 2:
            raise MonitorError(f"{name}: folds must be at least 2, got {folds}.")
        if "tsidm" in kwargs:
            raise MonitorError(f"{name} cannot refit a TS-IDM per fold; use DeploymentMonitor.fit(train, held_out, "
                               "tsidm=...) for the T-symmetry terms.")
        cls._check_options(name, data, quantile, window_quantile, kwargs)
        cls._transitions(data, "train", name)
        data = data.reshape(-1)
        trajectory = trajectory_ids(data)
        count = int(trajectory[-1]) + 1
        if count < folds:
            raise MonitorError(f"{name}: the data holds {count} trajectories, fewer than folds={folds}.")
        order = torch.randperm(count, generator=torch.Generator().manual_seed(seed))
        fold_of = torch.empty(count, dtype=torch.long)
        fold_of[order] = torch.arange(count) % folds
        fold = fold_of[trajectory]
        options = {"members": members, "num_cells": num_cells, "steps": steps, "max_states": max_states,
                   "precision": precision}
        held = [fold == k for k in range(int(folds))]
        # the fold detectors and the deployed ones (fitted to all of the data) train in one pass
        *fold_detectors, (dynamics, states) = cls._fit_detector_sets(
            [data[~rows] for rows in held] + [data], [seed + 1 + k for k in range(int(folds))] + [seed], **options)
        raw = {}
        for rows, (fold_dynamics, fold_states) in zip(held, fold_detectors):
            scores = cls(dynamics=fold_dynamics, states=fold_states, flag=False)._data_scores(data[rows])
            for term, value in scores.items():
                raw.setdefault(term, torch.empty(len(data)))[rows] = value
        monitor = cls(dynamics=dynamics, states=states, **kwargs)
        monitor._calibrate_scores(raw, trajectory, quantile, window_quantile)
        monitor.metadata = {"calibration": f"cross_fit_{int(folds)}", "train_transitions": len(data),
                            "calibration_transitions": len(data), "seed": seed}
        return monitor

    def _data_scores(self, data: TensorDictBase, batch_size: int = 2048) -> dict[str, torch.Tensor]:
        keys = (self.observation_key, self.action_key, ("next", self.observation_key))
        missing = [key for key in keys if unravel_key(key) not in data.keys(True)]
        if missing:
            raise MonitorError(f"{type(self).__name__}: the data has no {missing} "
                               f"(keys: {sorted(map(str, data.keys(True, True)))}).")
        data = data.reshape(-1)
        chunks = [self.raw_scores(*(chunk.get(key) for key in keys)) for chunk in data.split(batch_size)]
        return {term: torch.cat([chunk[term] for chunk in chunks]) for term in self.terms}

    # ----------------------------------------------------------- tensordicts
    def _write(self, next_tensordict: TensorDictBase, scores: dict[str, torch.Tensor]) -> TensorDictBase:
        for key, value in scores.items():
            next_tensordict.set(key, value.unsqueeze(-1))
        if self.flag:
            next_tensordict.set(FLAG_KEY, self.is_ood(scores[SCORE_KEY]).unsqueeze(-1))
        return next_tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # The transition (s, a, s') is complete only now: s and a at the root, s' in the step's output.
        scores = self.scores(tensordict.get(self.observation_key), tensordict.get(self.action_key),
                             next_tensordict.get(self.observation_key))
        batch = next_tensordict.batch_size
        device = scores[SCORE_KEY].device
        recent = tensordict.get(RECENT_KEY, None)
        count = tensordict.get(COUNT_KEY, None)
        if recent is None or count is None:  # stepped without a reset through this transform
            recent = torch.zeros(*batch, self.window, device=device)
            count = torch.zeros(*batch, 1, dtype=torch.long, device=device)
        mean, recent, count = self.update_window(recent, count, scores[SCORE_KEY])
        self._write(next_tensordict, {**scores, WINDOW_KEY: mean.float()})
        next_tensordict.set(RECENT_KEY, recent)
        next_tensordict.set(COUNT_KEY, count)
        if self.flag:
            self._require_calibration("the 'ood_alarm'")
            next_tensordict.set(ALARM_KEY, (mean > self.window_threshold).unsqueeze(-1))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # No transition has happened yet: zeros, an empty window, and no flag.
        batch, device = tensordict_reset.batch_size, tensordict_reset.device
        zeros = torch.zeros(batch, device=device)
        for key in (*self.terms, SCORE_KEY, WINDOW_KEY):
            tensordict_reset.set(key, zeros.unsqueeze(-1))
        tensordict_reset.set(RECENT_KEY, torch.zeros(*batch, self.window, device=device))
        tensordict_reset.set(COUNT_KEY, torch.zeros(*batch, 1, dtype=torch.long, device=device))
        if self.flag:
            for key in (FLAG_KEY, ALARM_KEY):
                tensordict_reset.set(key, torch.zeros(*batch, 1, dtype=torch.bool, device=device))
        return tensordict_reset

    def _score_transitions(self, tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = tensordict.get("next", None)
        if next_tensordict is None:
            raise MonitorError(f"{type(self).__name__}: the tensordict has no 'next' entry; the monitor scores "
                               "transitions (observation, action, ('next', observation)).")
        raw = self._data_scores(tensordict.select(self.observation_key, self.action_key,
                                                  ("next", self.observation_key)))
        scores = {**raw, SCORE_KEY: self.ood_score(self.standardize(raw))}
        shape = tensordict.batch_size
        self._write(next_tensordict, {key: value.reshape(shape) for key, value in scores.items()})
        return tensordict

    def _call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Called on whole transitions outside an env (in an env, _step runs instead).
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
                               f"spec shape {tuple(in_spec.shape)}, but the monitor was fitted to observations of "
                               f"size {self.observation_dim}: it was made for another environment.")
        batch, device = observation_spec.shape, observation_spec.device
        for key in (*self.terms, SCORE_KEY, WINDOW_KEY):
            observation_spec[key] = Unbounded(shape=batch + (1,), dtype=torch.float32, device=device)
        observation_spec[RECENT_KEY] = Unbounded(shape=batch + (self.window,), dtype=torch.float32, device=device)
        observation_spec[COUNT_KEY] = Unbounded(shape=batch + (1,), dtype=torch.long, device=device)
        if self.flag:
            for key in (FLAG_KEY, ALARM_KEY):
                observation_spec[key] = Categorical(2, shape=batch + (1,), dtype=torch.bool, device=device)
        return observation_spec

    def transform_action_spec(self, action_spec: TensorSpec) -> TensorSpec:
        spec = action_spec[self.action_key] if isinstance(action_spec, Composite) else action_spec
        if self.action_dim is not None and spec.shape[-1:] != (self.action_dim,):
            raise MonitorError(f"{type(self).__name__}: the environment's action {self.action_key!r} has spec "
                               f"shape {tuple(spec.shape)}, but the monitor was fitted to actions of size "
                               f"{self.action_dim}: it was made for another environment.")
        return action_spec

    # ------------------------------------------------------------- save/load
    def save(self, path: str | os.PathLike, metadata: dict[str, Any] | None = None) -> None:
        """Writes the detectors (configs and weights), the calibration and the options atomically."""
        def weights(module):
            return {k: v.detach().cpu() for k, v in module.state_dict().items()}

        atomic_save({
            "format": self.CHECKPOINT_FORMAT,
            "tsidm": None if self.tsidm is None else self.tsidm.checkpoint_payload(),
            "dynamics": None if self.dynamics is None else {
                "observation_dim": self.dynamics.observation_dim, "action_dim": self.dynamics.action_dim,
                "members": self.dynamics.members, "num_cells": list(self.dynamics.num_cells),
                "state_dict": weights(self.dynamics)},
            "states": None if self.states is None else {"state_dict": weights(self.states)},
            "score": self.score_key, "combine": list(self.combine), "window": self.window,
            "dim_reduction": self.dim_reduction,
            "calibration": {k: v.detach().cpu() for k, v in self.state_dict().items()
                            if k in ("term_loc", "term_scale", "threshold", "window_threshold", "quantile",
                                     "window_quantile")},
            "metadata": {**self.metadata, **(metadata or {})},
        }, path)

    @classmethod
    def load(cls, path: str | os.PathLike, *, observation_dim: int | None = None, action_dim: int | None = None,
             **kwargs) -> "DeploymentMonitor":
        """Rebuilds a monitor written by :meth:`save` (read with ``weights_only``); ``observation_dim`` and
        ``action_dim`` refuse another task's. ``kwargs`` (``flag``, the keys) go to the constructor."""
        fixed = sorted(set(kwargs) & {"score", "combine", "window", "dim_reduction", "tsidm", "dynamics", "states"})
        if fixed:
            raise MonitorError(f"{cls.__name__}.load: {fixed} are part of the saved monitor and cannot be changed "
                               "at load time; build a new monitor and calibrate it.")
        payload = load_checkpoint(path, cls.CHECKPOINT_FORMAT)
        try:
            tsidm = None if payload["tsidm"] is None else TSIDM.from_payload(
                payload["tsidm"], path, observation_dim=observation_dim, action_dim=action_dim)
            dynamics = states = None
            if payload["dynamics"] is not None:
                d = payload["dynamics"]
                dynamics = DynamicsEnsemble(d["observation_dim"], d["action_dim"], members=d["members"],
                                            num_cells=tuple(d["num_cells"]))
                dynamics.load_state_dict(d["state_dict"])
            if payload["states"] is not None:
                bank = payload["states"]["state_dict"]["bank"]
                states = NearestStateDistance.empty(bank.shape[-1], bank.shape[0])
                states.load_state_dict(payload["states"]["state_dict"])
            monitor = cls(tsidm=tsidm, dynamics=dynamics, states=states, score=payload["score"],
                          combine=payload["combine"], window=payload["window"],
                          dim_reduction=payload["dim_reduction"], observation_dim=observation_dim,
                          action_dim=action_dim, **kwargs)
            calibration = payload["calibration"]
            expected = {"term_loc", "term_scale", "threshold", "window_threshold", "quantile", "window_quantile"}
            if set(calibration) != expected:
                raise KeyError(f"calibration entries {sorted(calibration)}, expected {sorted(expected)}")
            monitor.load_state_dict(calibration, strict=False)
        except MonitorError as err:
            raise CheckpointError(f"{path}: {err}") from None
        except (AttributeError, KeyError, RuntimeError, TypeError, ValueError) as err:
            raise CheckpointError(f"{path} is a damaged {cls.CHECKPOINT_FORMAT!r} checkpoint: "
                                  f"{type(err).__name__}: {err}") from None
        monitor.metadata = dict(payload.get("metadata", {}))
        return monitor

    def __repr__(self) -> str:
        detectors = [name for name in ("tsidm", "dynamics", "states") if getattr(self, name) is not None]
        return (f"{type(self).__name__}(detectors={detectors}, score={self.score_key!r}, combine={list(self.combine)}, "
                f"window={self.window}, threshold={float(self.threshold):.4g}, "
                f"window_threshold={float(self.window_threshold):.4g}, observation_dim={self.observation_dim}, "
                f"action_dim={self.action_dim})")
