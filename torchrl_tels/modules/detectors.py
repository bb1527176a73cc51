"""Two simple detectors of transitions a dataset does not contain: a one-step dynamics ensemble and
the distance to the nearest data state.

Both work in a normalized state space (the data's per-dimension mean and standard deviation) and
score a batch of transitions :math:`(s, a, s')` with one number each, larger meaning farther from
the data. They are plain tensor programs, so :func:`torch.export.export` can trace them.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["DynamicsEnsemble", "NearestStateDistance", "fit_ensembles"]


BANK_SLICE = 2048  # bank states per distance product in NearestStateDistance


def _normalization(values: torch.Tensor, eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    return values.mean(0), values.std(0).clamp_min(eps)


class DynamicsEnsemble(nn.Module):
    r"""``members`` one-step models :math:`f_k(s, a) \approx \Delta = s' - s`, each fitted on its own random minibatches.

    States are normalized by the data's mean and standard deviation and the target step
    :math:`\Delta` by its own, so every dimension of the residual counts in units of its typical
    step. The members are stacked weight tensors applied with one batched matrix product, so the
    ensemble costs about one network of ``members`` times the width.

    :meth:`scores` returns, per transition,

    * ``residual``: :math:`\|\bar f(s, a) - \Delta\|_2^2`, the miss of the members' mean prediction:
      large where the plant does something the data never showed;
    * ``disagreement``: :math:`\sum_i \mathrm{Var}_k f_{k,i}(s, a)`, the members' spread: large
      where the data did not pin the model down (the epistemic term of model-based offline RL).

    Args:
        observation_dim, action_dim (int): sizes of :math:`s` and :math:`a`.

    Keyword Args:
        members (int): ensemble size. Defaults to 5.
        num_cells (sequence of int): hidden widths. Defaults to ``(200, 200)``.
    """

    def __init__(self, observation_dim: int, action_dim: int, *, members: int = 5,
                 num_cells: tuple[int, ...] = (200, 200)) -> None:
        super().__init__()
        if int(members) < 1:
            raise ValueError(f"DynamicsEnsemble needs at least one member, got members={members}.")
        self.observation_dim, self.action_dim, self.members = int(observation_dim), int(action_dim), int(members)
        self.num_cells = tuple(int(c) for c in num_cells)
        sizes = (self.observation_dim + self.action_dim, *self.num_cells, self.observation_dim)
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default initialization, per member
            self.weights.append(nn.Parameter(torch.empty(self.members, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(self.members, 1, fan_out).uniform_(-bound, bound)))
        for name in ("obs_loc", "obs_scale", "delta_loc", "delta_scale"):
            self.register_buffer(name, torch.zeros(self.observation_dim) if "loc" in name
                                 else torch.ones(self.observation_dim))

    def predict(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's normalized step prediction, shape ``(members, *batch, observation_dim)``."""
        batch = observation.shape[:-1]
        s = observation.to(self.obs_loc.dtype).reshape(1, -1, self.observation_dim).expand(self.members, -1, -1)
        a = action.to(s.dtype).reshape(1, -1, self.action_dim).expand(self.members, -1, -1)
        return self._members_forward(s, a).reshape(self.members, *batch, self.observation_dim)

    def normalized_step(self, observation: torch.Tensor, next_observation: torch.Tensor) -> torch.Tensor:
        delta = next_observation.to(self.obs_loc.dtype) - observation.to(self.obs_loc.dtype)
        return (delta - self.delta_loc) / self.delta_scale

    def scores(self, observation: torch.Tensor, action: torch.Tensor,
               next_observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(``residual``, ``disagreement``), each of shape ``observation.shape[:-1]``."""
        prediction = self.predict(observation, action)
        target = self.normalized_step(observation, next_observation)
        residual = (prediction.mean(0) - target).pow(2).sum(-1)
        disagreement = prediction.var(0, unbiased=False).sum(-1)
        return residual, disagreement

    def fit(self, observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor, *,
            steps: int = 3000, batch_size: int = 256, lr: float = 1e-3, seed: int = 0,
            precision: str = "fp32") -> list[float]:
        """Sets the normalizations from the data, then trains every member on its own random batches
        (Adam, mean squared error of the normalized step). Returns the loss every 100 steps.

        ``precision="bf16"`` runs the forward passes under bf16 autocast (the weights and the scores stay fp32)."""
        return fit_ensembles([self], [(observation, action, next_observation)], seeds=[seed], steps=steps,
                             batch_size=batch_size, lr=lr, precision=precision)[0]

    def _members_forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        # observation (members, B, d): member k sees its own batch.
        s = (observation - self.obs_loc) / self.obs_scale
        return _stacked_mlp(torch.cat([s, action], -1), self.weights, self.biases)

    def extra_repr(self) -> str:
        return f"observation_dim={self.observation_dim}, action_dim={self.action_dim}, members={self.members}, " \
               f"num_cells={self.num_cells}"


def _stacked_mlp(x: torch.Tensor, weights, biases) -> torch.Tensor:
    # x (members, B, d_in), weights[i] (members, d_i, d_i+1): one batched product per layer for all members.
    last = len(weights) - 1
    for i, (weight, bias) in enumerate(zip(weights, biases)):
        x = torch.baddbmm(bias, x, weight)
        if i < last:
            x = torch.relu(x)
    return x


def fit_ensembles(ensembles: Sequence[DynamicsEnsemble], transitions: Sequence[tuple[torch.Tensor, ...]], *,
                  seeds: Sequence[int], steps: int = 3000, batch_size: int = 256, lr: float = 1e-3,
                  precision: str = "fp32") -> list[list[float]]:
    """Trains each ``ensembles[j]`` on its own ``transitions[j]`` = (observation, action, next_observation)
    exactly as :meth:`DynamicsEnsemble.fit` would alone, but all of them at once.

    Each ensemble's normalizations come from its own data and its batches from its own generator
    (seeded by ``seeds[j]``). The members of all of them are stacked into one batched product per
    layer, and the objective is the sum of the ensembles' own losses, so each ensemble's gradient,
    and with Adam's per-entry moments each update, is the one it would get alone. Stacking pays
    the per-step overhead (launches, the optimizer, the Python loop) once for all: a cross-fitted
    monitor trains ``folds + 1`` ensembles. Returns each ensemble's loss every 100 steps.
    """
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"DynamicsEnsemble.fit: precision must be 'fp32' or 'bf16', got {precision!r}.")
    if not (len(ensembles) == len(transitions) == len(seeds)) or not ensembles:
        raise ValueError(f"fit_ensembles needs one (observation, action, next_observation) and one seed per "
                         f"ensemble, got {len(ensembles)} ensembles, {len(transitions)} datasets, {len(seeds)} seeds.")
    shapes = {(e.observation_dim, e.action_dim, e.num_cells) for e in ensembles}
    if len(shapes) > 1:
        raise ValueError(f"fit_ensembles stacks ensembles of one architecture, got {sorted(shapes)}.")
    device = transitions[0][0].device
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")
    inputs, targets, generators = [], [], []
    for ensemble, (observation, action, next_observation), seed in zip(ensembles, transitions, seeds):
        observation, action, next_observation = observation.float(), action.float(), next_observation.float()
        ensemble.obs_loc, ensemble.obs_scale = _normalization(observation)
        ensemble.delta_loc, ensemble.delta_scale = _normalization(next_observation - observation)
        inputs.append(torch.cat([(observation - ensemble.obs_loc) / ensemble.obs_scale, action], -1))
        targets.append(ensemble.normalized_step(observation, next_observation))
        generators.append(torch.Generator(device=device).manual_seed(int(seed)))
    members = [e.members for e in ensembles]
    layers = len(ensembles[0].weights)
    weights = [torch.cat([e.weights[i].detach() for e in ensembles]).requires_grad_() for i in range(layers)]
    biases = [torch.cat([e.biases[i].detach() for e in ensembles]).requires_grad_() for i in range(layers)]
    optim = torch.optim.Adam([*weights, *biases], lr=lr)
    history = [[] for _ in ensembles]
    for step in range(int(steps)):
        batch, target = [], []
        for x, y, m, generator in zip(inputs, targets, members, generators):
            index = torch.randint(len(x), (m, batch_size), generator=generator, device=device)
            batch.append(x[index])
            target.append(y[index])
        with autocast:
            prediction = _stacked_mlp(torch.cat(batch), weights, biases)
        per_member = (prediction.float() - torch.cat(target)).pow(2).sum(-1).mean(-1)
        losses = torch.stack([chunk.mean() for chunk in per_member.split(members)])
        optim.zero_grad(set_to_none=True)
        losses.sum().backward()
        optim.step()
        if step % 100 == 0 or step == steps - 1:
            for record, value in zip(history, losses.tolist()):
                record.append(value)
    with torch.no_grad():
        for i in range(layers):
            for ensemble, weight, bias in zip(ensembles, weights[i].split(members), biases[i].split(members)):
                ensemble.weights[i].copy_(weight)
                ensemble.biases[i].copy_(bias)
    for ensemble in ensembles:
        ensemble.eval()
    return history


class NearestStateDistance(nn.Module):
    r"""The Euclidean distance from :math:`s'` to the nearest stored data state, in normalized units.

    Stores up to ``max_states`` of the data's states (a seeded random subset beyond that), each
    dimension normalized by the data's mean and standard deviation. The distance is computed as
    :math:`\sqrt{\max(0, \|x\|^2 + \min_b (\|b\|^2 - 2 x \cdot b))}`, which traces and exports; a call
    builds a (batch, bank) matrix, so score large sets in batches (the monitor's ``_data_scores`` does).

    Args:
        states (Tensor): the data's states, shape ``(N, observation_dim)``.

    Keyword Args:
        max_states (int): how many states to keep. Defaults to 20000.
        seed (int): seed of the subset. Defaults to 0.
    """

    def __init__(self, states: torch.Tensor, *, max_states: int = 20000, seed: int = 0) -> None:
        super().__init__()
        states = states.reshape(-1, states.shape[-1]).float()
        if len(states) == 0:
            raise ValueError("NearestStateDistance needs at least one state.")
        loc, scale = _normalization(states)
        if len(states) > max_states:
            keep = torch.randperm(len(states), generator=torch.Generator().manual_seed(seed))[:max_states]
            states = states[keep.to(states.device)]
        bank = (states - loc) / scale
        self.register_buffer("obs_loc", loc)
        self.register_buffer("obs_scale", scale)
        self.register_buffer("bank", bank)
        self.register_buffer("bank_sq", bank.pow(2).sum(-1))

    @classmethod
    def empty(cls, observation_dim: int, size: int) -> "NearestStateDistance":
        """A bank of ``size`` zero states, for loading a state dict into."""
        module = cls.__new__(cls)
        nn.Module.__init__(module)
        for name, shape in (("obs_loc", (observation_dim,)), ("obs_scale", (observation_dim,)),
                            ("bank", (size, observation_dim)), ("bank_sq", (size,))):
            module.register_buffer(name, torch.zeros(shape))
        return module

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """Distance of each state (shape ``(*batch, observation_dim)``) to the bank, shape ``batch``."""
        batch = state.shape[:-1]
        x = ((state.to(self.bank.dtype) - self.obs_loc) / self.obs_scale).reshape(-1, self.bank.shape[-1])
        # min_b ||x - b||^2 = ||x||^2 + min_b (||b||^2 - 2 x.b): one fused product per slice of the bank, each
        # (batch, slice) matrix reduced while it is still in cache; the whole (batch, bank) matrix at once went
        # to memory and back, four times slower over a dataset (benchmarks/monitor_scoring.py). The slices are
        # fixed by the bank's size, so the loop traces and exports.
        closest = torch.stack([torch.addmm(self.bank_sq[start:start + BANK_SLICE], x,
                                           self.bank[start:start + BANK_SLICE].T, alpha=-2.0).amin(-1)
                               for start in range(0, self.bank.shape[0], BANK_SLICE)]).amin(0)
        return (x.pow(2).sum(-1) + closest).clamp_min(0.0).sqrt().reshape(batch)

    def extra_repr(self) -> str:
        return f"states={self.bank.shape[0]}, observation_dim={self.bank.shape[1]}"
