"""Several seeds of one loss module, trained in one process as one batched update.

Each seed keeps its own loss module (its own initialisation, buffers and
attributes); :class:`StackedLoss` stacks their parameters and buffers along a
new leading dimension and evaluates the first module with each seed's slice
under :func:`torch.vmap`. One backward pass then gives every seed exactly the
gradient its own run would get (the seeds share no parameter, so the sum over
seeds separates), and one elementwise optimizer over the stacked leaves is the
seeds' own optimizers side by side.

:class:`SeedRNG` keeps one stream of torch's global RNG per seed, so that what a
seed draws outside the vmapped call (its replay-buffer indices, its
initialisation) is what it draws in a single-seed run.

What differs from single-seed runs: random draws *inside* the vmapped call
(dropout) come from the shared global stream, so with dropout a seed matches
its single-seed run in distribution, not draw for draw (its batches too, since a
single-seed run draws dropout masks and batch indices from one stream); in-place
sampling (``Distribution.rsample``) cannot run under vmap at all; plain Python attributes
of the loss (a float option) are the first module's for every seed; and a
loss's data-dependent input checks (``check_inputs``) are off under vmap.
"""
from __future__ import annotations

import contextlib
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_tels.errors import CheckpointError

__all__ = ["SeedAxis", "SeedRNG", "StackedLoss"]


class StackedLoss:
    """The parameters of ``losses`` (one module per seed, same structure) stacked, and one vmapped forward.

    Args:
        losses: one loss module per seed. The first one is the template the
            stacked parameters are swapped into; each module keeps its own
            parameters untouched until :meth:`write_back`.

    ``params`` holds every parameter and buffer of the modules with a leading
    seed dimension; a leaf needs a gradient exactly where the first module's
    does. Calling the object with a batch of shape ``[n_seeds, batch]`` returns
    the loss tensordict with a leading seed dimension.
    """

    def __init__(self, losses: Sequence[torch.nn.Module]):
        if not losses:
            raise ValueError("StackedLoss needs at least one loss module.")
        self.losses = list(losses)
        self.template = self.losses[0]
        layouts = [TensorDict.from_module(loss) for loss in self.losses]
        keys = set(layouts[0].keys(True, True))
        for k, layout in enumerate(layouts[1:], 1):
            if set(layout.keys(True, True)) != keys:
                raise ValueError(f"StackedLoss: the module of seed index {k} has other parameters than the first.")
        self.params = torch.stack([layout.detach() for layout in layouts]).clone()
        for key, leaf in layouts[0].items(True, True):
            if leaf.requires_grad:
                self.params.get(key).requires_grad_()
        self._call = torch.vmap(self._forward, (0, 0), randomness="different")

    def __len__(self) -> int:
        return len(self.losses)

    def _forward(self, params: TensorDictBase, batch: TensorDictBase) -> TensorDictBase:
        with params.to_module(self.template):
            return self.template(batch)

    def __call__(self, batches: TensorDictBase) -> TensorDictBase:
        if batches.batch_size[:1] != torch.Size([len(self)]):
            raise ValueError(f"StackedLoss: expected batches with leading size {len(self)} (one per seed), "
                             f"got batch size {tuple(batches.batch_size)}.")
        # A loss's own input checks (``check_inputs``) branch on the data, which vmap cannot do.
        checks = getattr(self.template, "check_inputs", None)
        if checks:
            self.template.check_inputs = False
        try:
            return self._call(self.params, batches)
        finally:
            if checks:
                self.template.check_inputs = checks

    def trainable(self, prefix: str | None = None) -> list[torch.Tensor]:
        """The stacked leaves that need a gradient (under ``prefix`` only, if given)."""
        source = self.params if prefix is None else self.params.get(prefix)
        return [leaf for leaf in source.values(True, True) if leaf.requires_grad]

    def parameters(self) -> list[torch.Tensor]:
        """What an optimizer of every seed at once steps: :meth:`trainable`, as ``Module.parameters`` reads."""
        return self.trainable()

    def share(self, key: str, source: "StackedLoss", source_key: str | None = None) -> None:
        """Makes ``params[key]`` a gradient-free view of ``source.params[source_key]``.

        Where a loss reads another loss's live weights (the guide reads V), the
        stacked copies must stay views too, or the reader would see stale weights.
        """
        self.params.set(key, source.params.get(source_key or key).detach())

    def write_back(self) -> None:
        """Copies each seed's slice into its own module (before evaluating or saving it)."""
        with torch.no_grad():
            for k, loss in enumerate(self.losses):
                TensorDict.from_module(loss).data.update_(self.params[k].data)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {".".join(key): leaf.detach() for key, leaf in self.params.items(True, True)}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        with torch.no_grad():
            for key, leaf in self.params.items(True, True):
                name = ".".join(key)
                if name not in state or state[name].shape != leaf.shape:
                    raise CheckpointError(f"the saved stacked state has no tensor {name!r} of shape "
                                          f"{tuple(leaf.shape)}: it was written for other seeds or networks.")
                leaf.copy_(state[name])


class SeedRNG:
    """One stream of torch's global RNG (and CUDA's, where there is one) per seed.

    ``with rng.use(k):`` runs its body on seed ``k``'s stream and leaves the
    outer stream as it was. A stream starts from ``torch.manual_seed(seed)``
    (:meth:`start`), or from a saved :meth:`state_dict`. numpy's and Python's
    generators are not swapped: nothing a seed draws per step uses them.
    """

    def __init__(self, n_seeds: int):
        self.states: list[dict | None] = [None] * n_seeds

    @staticmethod
    def _get() -> dict:
        state = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            state["cuda"] = torch.cuda.get_rng_state_all()
        return state

    @staticmethod
    def _set(state: dict) -> None:
        torch.set_rng_state(state["torch"])
        if "cuda" in state and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda"])

    def start(self, k: int, seed: int) -> None:
        outer = self._get()
        torch.manual_seed(seed)
        self.states[k] = self._get()
        self._set(outer)

    @contextlib.contextmanager
    def use(self, k: int):
        if self.states[k] is None:
            raise RuntimeError(f"SeedRNG: stream {k} was never started.")
        outer = self._get()
        self._set(self.states[k])
        try:
            yield
        finally:
            self.states[k] = self._get()
            self._set(outer)

    def state_dict(self) -> list:
        return list(self.states)

    def load_state_dict(self, states: list) -> None:
        if len(states) != len(self.states):
            raise CheckpointError(f"the checkpoint holds RNG streams for {len(states)} seeds, this run has "
                                  f"{len(self.states)}.")
        self.states = list(states)


class SeedAxis:
    """The seeds one process trains, ``K >= 1``, and how their modules, RNG streams and batches line up.

    A plain run (``stacked=False``, one seed) trains its loss modules as they are, on torch's global RNG: the
    ordinary training loop. A stacked run (``stacked=True``) stacks the seeds' loss modules
    (:class:`StackedLoss`) and gives each seed its own stream (:class:`SeedRNG`), so that each seed is built and
    draws its batches as in its own plain run; its losses carry a leading seed dimension. Code written against
    this class trains either without knowing which.
    """

    def __init__(self, seeds: Sequence[int], *, stacked: bool, rng: SeedRNG | None = None):
        if not stacked and len(seeds) != 1:
            raise ValueError(f"SeedAxis: a plain run trains one seed, got {list(seeds)}.")
        self.seeds, self.stacked = list(seeds), stacked
        self.rng = (rng or SeedRNG(len(self.seeds))) if stacked else None

    def __len__(self) -> int:
        return len(self.seeds)

    @property
    def labels(self) -> list[str] | None:
        """Names of the seeds for messages about one of them (``FiniteWatch``); ``None`` for a plain run."""
        return [f"seed {seed}" for seed in self.seeds] if self.stacked else None

    def prefix(self, k: int) -> str:
        """The logger prefix of seed ``k``'s scalars."""
        return f"seed{self.seeds[k]}/" if self.stacked else ""

    def start(self, k: int, seed: int) -> None:
        """Starts seed ``k``'s stream from ``seed`` (a plain run: torch's global stream)."""
        if self.stacked:
            self.rng.start(k, seed)
        else:
            torch.manual_seed(seed)

    def seed_shared_stream(self, seed: int) -> None:
        """Seeds the global stream that a stacked update draws from inside ``vmap`` (dropout); a plain run's
        global stream is its own and is left as it is."""
        if self.stacked:
            torch.manual_seed(seed)

    def use(self, k: int):
        """A context running its body on seed ``k``'s stream."""
        return self.rng.use(k) if self.stacked else contextlib.nullcontext()

    def stack(self, losses: Sequence[torch.nn.Module]):
        """The module one update trains: the seed's own loss, or the seeds' losses stacked."""
        return StackedLoss(losses) if self.stacked else losses[0]

    def sample(self, buffers: Sequence) -> TensorDictBase:
        """One batch per seed, each drawn from its own buffer on its own stream (stacked: ``[seeds, batch]``)."""
        if not self.stacked:
            return buffers[0].sample()
        batches = []
        for k, buffer in enumerate(buffers):
            with self.use(k):
                batches.append(buffer.sample())
        return torch.stack(batches)

    def of(self, value, k: int):
        """Seed ``k``'s entry of a value with a leading seed dimension (the value itself for a plain run)."""
        return value[k] if self.stacked else value

    def state_modules(self) -> dict:
        """The seeds' RNG streams as a checkpointed module (a plain run's global RNG travels with every state)."""
        return {"seed_rng": self.rng} if self.stacked else {}
