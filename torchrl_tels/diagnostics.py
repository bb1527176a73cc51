"""Numbers that show whether T-symmetry is doing anything, and whether a policy has frozen.

Eq. (7) can lower ℓ_dyn and ℓ_T-sym by shrinking the latent space (see
:class:`~torchrl_tels.objectives.TSIDMLoss`, "Latent scale"); a policy acting
through Eq. (11) can settle into small proposals for which h_inv returns a
near-constant action. Both show up as numbers here.

:func:`action_chain_statistics` splits a trained actor's action error on its data into the part its
TS-IDM makes (Eq. 11 fed the true next latent state) and the part the guide adds (its proposal instead):
how much an objective costs the inverse dynamics, and whether the guide proposes the data's steps.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY, LatentActionHead, StateEncoder
from torchrl_tels.modules.tsidm import TSIDM

__all__ = ["latent_statistics", "rollout_statistics", "action_chain_statistics", "awr_weight_statistics", "is_frozen",
           "is_off_data", "maze_cells", "FREEZE_RATIO", "OFF_DATA_RATIO"]

#: A rollout's proposals are "off the data" when their RMS latent step exceeds the data's this many times.
OFF_DATA_RATIO = 4.0
#: A rollout is "frozen" when both its proposed latent step and its action spread
#: fall below this fraction of the data's.
FREEZE_RATIO = 0.25


@torch.no_grad()
def latent_statistics(tsidm: TSIDM, observation: torch.Tensor, next_observation: torch.Tensor) -> dict[str, float]:
    """``latent_rms`` (RMS spread of :math:`z_s` per dimension) and ``latent_step_rms``
    (:math:`\\sqrt{\\mathbb E\\|z_{s'} - z_s\\|^2}`) of a TS-IDM on transitions."""
    z = tsidm.encode_states(observation)
    z_next = tsidm.encode_states(next_observation)
    return {
        "latent_rms": z.var(0).mean().sqrt().item(),
        "latent_step_rms": (z_next - z).pow(2).sum(-1).mean().sqrt().item(),
    }


def rollout_statistics(rollout: TensorDictBase, latent_key=LATENT_KEY, guide_key=GUIDE_KEY) -> dict[str, float]:
    r"""What one episode of a TELS actor did with its guide's proposals.

    * ``guide_step_rms``: :math:`\sqrt{\mathbb E_t\|\pi_g(z_t) - z_t\|^2}`, the proposed latent step.
    * ``action_std``: per-dimension std of the actions over time, averaged.
    * ``realized_error_ratio``: :math:`\sqrt{\mathbb E_t\|z_{t+1} - \pi_g(z_t)\|^2 / \mathbb E_t\|\pi_g(z_t) - z_t\|^2}`,
      how far the state the environment reached is from the one the guide proposed, against the size of
      the proposed step: 0 when Eq. (11)'s action lands exactly on the proposal, 1 when it does no better
      than staying put. The value term of Eq. (9) can only raise the return through proposals the chain
      realizes.
    * ``realized_step_cosine``: mean cosine between the step taken, :math:`z_{t+1} - z_t`, and the one proposed.

    The last two need two steps and a non-zero proposal; they are NaN otherwise.
    """
    for key in (latent_key, guide_key, "action"):
        if key not in rollout.keys(True):
            raise KeyError(f"rollout_statistics: the rollout has no {key!r}; was it made by a TELS actor?")
    latent, proposal = rollout.get(latent_key), rollout.get(guide_key)
    step = proposal - latent
    action = rollout.get("action").reshape(-1, rollout.get("action").shape[-1])
    action_std = action.std(0).mean().item() if action.shape[0] > 1 else 0.0
    proposed, taken = step[..., :-1, :], latent[..., 1:, :] - latent[..., :-1, :]
    proposed_size = proposed.pow(2).sum(-1).mean()
    if proposed.shape[-2] == 0 or proposed_size == 0:
        realized_error, cosine = float("nan"), float("nan")
    else:
        realized_error = ((taken - proposed).pow(2).sum(-1).mean() / proposed_size).sqrt().item()
        cosine = torch.nn.functional.cosine_similarity(taken, proposed, dim=-1).mean().item()
    return {"guide_step_rms": step.pow(2).sum(-1).mean().sqrt().item(), "action_std": action_std,
            "realized_error_ratio": realized_error, "realized_step_cosine": cosine}


@torch.no_grad()
def action_chain_statistics(actor: TensorDictSequential, data: TensorDictBase,
                            batch_size: int = 65536) -> dict[str, float]:
    r"""Where a TELS actor's action error on transitions comes from, over every transition (as Eq. 7
    and Eq. 9 train on them), ``batch_size`` at a time.

    * ``inverse_action_mse``: mean squared error of Eq. (11) fed the true next latent,
      :math:`\psi_a(h_{inv}(z_s, z_{s'}))` clipped to the actor's action bounds, against the data's
      action: the TS-IDM's part, whatever the actor's head options.
    * ``actor_action_mse``: the same for the actor as it acts (its head fed :math:`\pi_g(z_s)`,
      with its own options; random if it keeps h_inv's dropout on).
    * ``guide_step_ratio``: :math:`\sqrt{\mathbb E\|\pi_g(z_s) - z_s\|^2 / \mathbb E\|z_{s'} - z_s\|^2}`,
      1 when the guide proposes steps of the data's size.
    * ``guide_step_cosine``: mean cosine between the proposed step and the data's step.
    * ``guide_error_ratio``: :math:`\sqrt{\mathbb E\|\pi_g(z_s) - z_{s'}\|^2 / \mathbb E\|z_{s'} - z_s\|^2}`,
      the guide's error in predicting the next latent against the latent step: 0 for a perfect
      prediction, 1 for one no better than "stay put". On transitions held out from training it
      says whether the guide generalizes.

    ``actor`` is :func:`~torchrl_tels.modules.make_tels_actor`'s chain from observations (encoder,
    guide, Eq. 11 head), run deterministically on its own device.
    """
    encoder, head = (actor[0].module, actor[-1].module) if isinstance(actor, TensorDictSequential) else (None, None)
    if not (isinstance(encoder, StateEncoder) and isinstance(head, LatentActionHead)):
        raise ValueError("action_chain_statistics needs a TELS actor that starts from observations "
                         "(make_tels_actor(..., from_latent=False)): encoder, guide, Eq. (11) head.")
    observation_key, action_key = actor[0].in_keys[0], actor[-1].out_keys[0]
    tsidm, device = head.tsidm, next(actor.parameters()).device
    sums = dict.fromkeys(("inverse", "actor", "guide_step", "data_step", "cosine", "guide_error"), 0.0)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for batch in data.split(batch_size):
            batch = batch.to(device)
            acted = actor(TensorDict({observation_key: batch[observation_key]}, batch_size=batch.batch_size,
                                     device=device))
            latent, next_latent = acted.get(LATENT_KEY), tsidm.encode_state(batch["next", observation_key])
            inverse = tsidm.decode_action(tsidm.infer_latent_action(latent, next_latent))
            if head.low is not None or head.high is not None:
                inverse = inverse.clamp(head.low, head.high)
            data_step, guide_step = next_latent - latent, acted.get(GUIDE_KEY) - latent
            sums["inverse"] += (inverse - batch[action_key]).pow(2).mean(-1).sum().item()
            sums["actor"] += (acted.get(action_key) - batch[action_key]).pow(2).mean(-1).sum().item()
            sums["guide_step"] += guide_step.pow(2).sum().item()
            sums["data_step"] += data_step.pow(2).sum().item()
            sums["cosine"] += torch.nn.functional.cosine_similarity(guide_step, data_step, dim=-1).sum().item()
            sums["guide_error"] += (acted.get(GUIDE_KEY) - next_latent).pow(2).sum().item()
    count = data.numel()
    return {
        "inverse_action_mse": sums["inverse"] / count,
        "actor_action_mse": sums["actor"] / count,
        "guide_step_ratio": (sums["guide_step"] / sums["data_step"]) ** 0.5,
        "guide_step_cosine": sums["cosine"] / count,
        "guide_error_ratio": (sums["guide_error"] / sums["data_step"]) ** 0.5,
    }


def is_frozen(
    guide_step_rms: float,
    action_std: float,
    data_step_rms: float,
    data_action_std: float,
    ratio: float = FREEZE_RATIO,
) -> bool:
    """True when the policy proposes much smaller latent steps than the data takes and its
    actions barely vary: the guide → h_inv chain sits at a fixed point."""
    return guide_step_rms < ratio * data_step_rms and action_std < ratio * data_action_std


def is_off_data(guide_step_rms: float, data_step_rms: float, ratio: float = OFF_DATA_RATIO) -> bool:
    """True when the guide proposes latent steps far larger than any the data takes: the opposite
    failure to a freeze, where Eq. (11) asks h_inv for transitions it never saw."""
    return guide_step_rms > ratio * data_step_rms


def maze_cells(xy: torch.Tensor, cell_size: float = 4.0) -> torch.Tensor:
    """The maze cell of each (x, y), as integer (column, row) pairs: D4RL's AntMaze scales each maze cell to
    4 units, with the start cell centred on the origin."""
    return torch.floor(xy / cell_size + 0.5).long()


@torch.no_grad()
def awr_weight_statistics(guide_loss, encoded: TensorDictBase, regions: torch.Tensor | None = None,
                          chunk: int = 4096) -> dict:
    """Where Eq. (10)'s weights put the guide's attention, over every transition of the encoded data.

    ``effective_sample_fraction`` (Kish's ESS over n: 1 when all weigh the same), ``clipped_fraction``
    (weights at the clip), the advantage's mean, V's range on the data (``value_min``/``value_max``),
    and with ``regions`` (an (N, k) integer label per transition, e.g. :func:`maze_cells`) each region's
    share of the data and of the total weight.
    """
    from torchrl_tels.objectives.tsym_guide import effective_sample_fraction

    parts = [guide_loss.awr_weights(encoded[i:i + chunk]) for i in range(0, len(encoded), chunk)]
    advantage, weight, clipped = (torch.cat(p).float().reshape(-1) for p in zip(*parts))
    values = torch.cat([guide_loss._value(encoded[i:i + chunk].get(guide_loss.tensor_keys.latent))
                        for i in range(0, len(encoded), chunk)]).float()
    stats = {"effective_sample_fraction": effective_sample_fraction(weight).item(),
             "clipped_fraction": clipped.float().mean().item(), "advantage_mean": advantage.mean().item(),
             "value_min": values.min().item(), "value_max": values.max().item(), "transitions": len(weight)}
    if regions is not None:
        labels, index = torch.unique(regions.reshape(len(weight), -1), dim=0, return_inverse=True)
        data_share = torch.bincount(index, minlength=len(labels)).double() / len(weight)
        weight_share = torch.zeros(len(labels), dtype=torch.float64).index_add_(0, index, weight.double())
        weight_share /= weight_share.sum()
        stats["regions"] = {",".join(str(int(v)) for v in label): {"data_share": d.item(), "weight_share": w.item()}
                            for label, d, w in zip(labels, data_share, weight_share)}
    return stats
