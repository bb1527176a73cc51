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

from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY
from torchrl_tels.modules.tsidm import TSIDM

__all__ = ["latent_statistics", "rollout_statistics", "action_chain_statistics", "is_frozen", "is_off_data",
           "FREEZE_RATIO", "OFF_DATA_RATIO"]

#: A rollout's proposals are "off the data" when their RMS latent step exceeds the data's this many times.
OFF_DATA_RATIO = 4.0
#: A rollout is "frozen" when both its proposed latent step and its action spread
#: fall below this fraction of the data's.
FREEZE_RATIO = 0.25


@torch.no_grad()
def latent_statistics(tsidm: TSIDM, observation: torch.Tensor, next_observation: torch.Tensor) -> dict[str, float]:
    """``latent_rms`` (RMS spread of :math:`z_s` per dimension) and ``latent_step_rms``
    (:math:`\\sqrt{\\mathbb E\\|z_{s'} - z_s\\|^2}`) of a TS-IDM on transitions."""
    z = tsidm.encode_state(observation)
    z_next = tsidm.encode_state(next_observation)
    return {
        "latent_rms": z.var(0).mean().sqrt().item(),
        "latent_step_rms": (z_next - z).pow(2).sum(-1).mean().sqrt().item(),
    }


def rollout_statistics(rollout: TensorDictBase, latent_key=LATENT_KEY, guide_key=GUIDE_KEY) -> dict[str, float]:
    """``guide_step_rms`` (:math:`\\sqrt{\\mathbb E\\|\\pi_g(z) - z\\|^2}`) and ``action_std``
    (per-dimension std over time, averaged) of one episode of a TELS actor."""
    for key in (latent_key, guide_key, "action"):
        if key not in rollout.keys(True):
            raise KeyError(f"rollout_statistics: the rollout has no {key!r}; was it made by a TELS actor?")
    step = rollout.get(guide_key) - rollout.get(latent_key)
    action = rollout.get("action").reshape(-1, rollout.get("action").shape[-1])
    action_std = action.std(0).mean().item() if action.shape[0] > 1 else 0.0
    return {"guide_step_rms": step.pow(2).sum(-1).mean().sqrt().item(), "action_std": action_std}


@torch.no_grad()
def action_chain_statistics(actor: TensorDictSequential, tsidm: TSIDM, data: TensorDictBase) -> dict[str, float]:
    r"""Where a TELS actor's action error on transitions comes from (non-terminal ones: a terminal
    next state is no latent the actor could aim at).

    * ``inverse_action_mse``: mean squared error of the actor's own Eq. (11) head fed the true next
      latent, :math:`\psi_a(h_{inv}(z_s, z_{s'}))` against the data's action: the TS-IDM's share.
    * ``actor_action_mse``: the same for the whole actor, whose head is fed :math:`\pi_g(z_s)`.
    * ``guide_step_ratio``: :math:`\sqrt{\mathbb E\|\pi_g(z_s) - z_s\|^2 / \mathbb E\|z_{s'} - z_s\|^2}`,
      1 when the guide proposes steps of the data's size.
    * ``guide_step_cosine``: mean cosine between the proposed step and the data's step.

    ``actor`` is :func:`~torchrl_tels.modules.make_tels_actor`'s chain (encoder, guide, head), run
    deterministically on the actor's device.
    """
    device = next(actor.parameters()).device
    keep = ~data["next", "terminated"].reshape(-1)
    if not keep.any():
        raise ValueError("action_chain_statistics: every transition is terminal; there is no next latent to aim at.")
    data = data[keep].to(device)
    observation, action = data["observation"], data["action"]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        acted = actor(TensorDict({"observation": observation}, batch_size=[len(observation)], device=device))
        latent, next_latent = acted.get(LATENT_KEY), tsidm.encode_state(data["next", "observation"])
        head = actor[-1]
        inverse = head(TensorDict({LATENT_KEY: latent, GUIDE_KEY: next_latent}, batch_size=[len(observation)],
                                  device=device)).get(head.out_keys[0])
    data_step, guide_step = next_latent - latent, acted.get(GUIDE_KEY) - latent
    return {
        "inverse_action_mse": (inverse - action).pow(2).mean().item(),
        "actor_action_mse": (acted.get("action") - action).pow(2).mean().item(),
        "guide_step_ratio": (guide_step.pow(2).sum(-1).mean() / data_step.pow(2).sum(-1).mean()).sqrt().item(),
        "guide_step_cosine": torch.nn.functional.cosine_similarity(guide_step, data_step, dim=-1).mean().item(),
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
