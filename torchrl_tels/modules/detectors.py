"""Two simple detectors of transitions a dataset does not contain: a one-step dynamics ensemble and
the distance to the nearest data state.

Both work in a normalized state space (the data's per-dimension mean and standard deviation) and
score a batch of transitions :math:`(s, a, s')` with one number each, larger meaning farther from
the data. They are plain tensor programs, so :func:`torch.export.export` can trace them.
"""
from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["DynamicsEnsemble", "NearestStateDistance"]


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
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"DynamicsEnsemble.fit: precision must be 'fp32' or 'bf16', got {precision!r}.")
        autocast = torch.autocast(observation.device.type, dtype=torch.bfloat16, enabled=precision == "bf16")
        observation, next_observation = observation.float(), next_observation.float()
        action = action.float()
        self.obs_loc, self.obs_scale = _normalization(observation)
        self.delta_loc, self.delta_scale = _normalization(next_observation - observation)
        target = self.normalized_step(observation, next_observation)
        generator = torch.Generator(device=observation.device).manual_seed(seed)
        optim = torch.optim.Adam(self.parameters(), lr=lr)
        n, history = len(observation), []
        self.train()
        for step in range(int(steps)):
            index = torch.randint(n, (self.members, batch_size), generator=generator, device=observation.device)
            s, a = observation[index], action[index]
            with autocast:
                prediction = self._members_forward(s, a)
            loss = (prediction.float() - target[index]).pow(2).sum(-1).mean()
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            if step % 100 == 0 or step == steps - 1:
                history.append(loss.item())
        self.eval()
        return history

    def _members_forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        # observation (members, B, d): member k sees its own batch.
        s = (observation - self.obs_loc) / self.obs_scale
        x = torch.cat([s, action], -1)
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias, x, weight)
            if i < last:
                x = torch.relu(x)
        return x

    def extra_repr(self) -> str:
        return f"observation_dim={self.observation_dim}, action_dim={self.action_dim}, members={self.members}, " \
               f"num_cells={self.num_cells}"


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
        # min_b ||x - b||^2 = ||x||^2 + min_b (||b||^2 - 2 x.b): one fused product and one pass over the
        # (batch, bank) matrix, where the expanded sum made four.
        closest = torch.addmm(self.bank_sq, x, self.bank.T, alpha=-2.0).amin(-1)
        return (x.pow(2).sum(-1) + closest).clamp_min(0.0).sqrt().reshape(batch)

    def extra_repr(self) -> str:
        return f"states={self.bank.shape[0]}, observation_dim={self.bank.shape[1]}"
