"""TorchRL's stock offline baselines under the TELS evaluation protocol.

One function, :func:`train_baseline`, trains and evaluates one baseline on one
offline dataset with one seed and returns a dict laid out like the recipe's
``results.json``. The losses are TorchRL's own objectives, used as they come:

==============  ==============================================================
``iql``         :class:`torchrl.objectives.IQLLoss` on raw states
``iql_latent``  the same IQL on the latent states of a frozen TS-IDM
                (:class:`~torchrl_tels.envs.TSIDMEncoderTransform`; Fig. 4 left)
``td3bc``       :class:`torchrl.objectives.TD3BCLoss`
``bc``          :class:`torchrl.objectives.BCLoss` (deterministic tanh actor, MSE)
==============  ==============================================================

Hyperparameters (:data:`HYPERPARAMETERS`, each with its source):

* IQL: TorchRL's ``sota-implementations/iql`` offline config: 256x256 ReLU
  MLPs for actor, twin Q and V; TanhNormal actor (``tanh_loc=False``, scale
  ``biased_softplus_1.0`` with lower bound 0.1); expectile 0.7, temperature
  3.0, gamma 0.99, soft target update tau 0.005 on Q, L2 Q loss, Adam lr 3e-4
  for all three nets, one update of all three per step. States are **not**
  normalized and rewards are not rescaled, as in that implementation. The IQL
  paper (Kostrikov et al., 2022, App. B) rescales locomotion rewards by
  ``1000 / (max - min)`` of the dataset's episode returns; ``reward_scale=
  "return_range"`` does that (:func:`return_range_scale`).
* IQL in latent space: the same, with the networks reading ``"latent"``; the
  TS-IDM encoder normalizes states itself before encoding.
* TD3+BC: TorchRL's ``sota-implementations/td3_bc`` config: 256x256 ReLU MLPs,
  alpha 2.5, policy noise 0.2, noise clip 0.5, actor and target update every
  2 critic steps, gamma 0.99, tau 0.005 (polyak 0.995), L2 Q loss, Adam lr 3e-4
  with eps 1e-4. States are normalized with the dataset's mean and std
  (+1e-3), as in the TD3+BC paper (Fujimoto & Gu, 2021, Sec. 5); TorchRL's
  script leaves them raw.
* Mazes (:data:`MAZE_HYPERPARAMETERS`): IQL and IQL-latent take the IQL
  paper's AntMaze values, expectile 0.9, temperature 10 and rewards r - 1, and
  its authors' actor and action handling (:data:`IQL_AUTHORS_ACTOR`): a Gaussian
  with a tanh mean instead of TorchRL's tanh-squashed Gaussian, dataset actions
  clipped to +-(1 - 1e-5), a cosine-decayed actor learning rate; states normalized
  (the authors' are raw: see the note at :data:`MAZE_HYPERPARAMETERS`). Where TorchRL's
  recipe differs: its actor is a TanhNormal and its lr constant.
* BC: TD3+BC's actor without its Q term: the same deterministic 256x256 ReLU
  MLP with a tanh output, the same normalized states, ``BCLoss`` with an L2
  loss, Adam lr 3e-4.

Protocol (the recipe's, ``recipes/tels_offline.py``): batch 256, an evaluation
every ``eval_interval`` steps and after the last one, each of
``eval_episodes`` deterministic episodes through
:func:`torchrl_tels.envs.evaluate_policy` with seed
``seed * 100_000 + step``, D4RL-normalized; the final score is the mean of
the last ``eval_last_n`` (10) evaluations.
"""
from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from tensordict.nn.distributions import AddStateIndependentNormalScale, NormalParamExtractor
from torch import nn
from torchrl.envs import Compose, DoubleToFloat, EnvBase, ObservationNorm, TransformedEnv
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import BCLoss, IQLLoss, SoftUpdate, TD3BCLoss

from torchrl_tels.checkpoint import file_sha256
from torchrl_tels.data import load_dataset, make_offline_replay_buffer
from torchrl_tels.envs import evaluate_episodes, get_task, make_eval_envs, normalized_score, TSIDMEncoderTransform
from torchrl_tels.envs.evaluation import success_rate
from torchrl_tels.config import resolve_device
from torchrl_tels.record import final_success_rate
from torchrl_tels.training import FiniteWatch

__all__ = ["ADROIT_HYPERPARAMETERS", "HYPERPARAMETERS", "IQL_AUTHORS_ACTOR", "MAZE_HYPERPARAMETERS", "METHODS", "check_reward_scale", "return_range_scale",
           "train_baseline"]

METHODS = ("iql", "td3bc", "bc", "iql_latent")

_IQL = {
    "hidden_sizes": [256, 256],
    "activation": "relu",
    "lr": 3e-4,
    "weight_decay": 0.0,
    "expectile": 0.7,
    "temperature": 3.0,
    "gamma": 0.99,
    "tau": 0.005,
    "loss_function": "l2",
    "default_policy_scale": 1.0,
    "scale_lb": 0.1,
    "normalize_observations": False,
    "reward_scale": 1.0,
    "reward_bias": 0.0,
    "actor": "tanh_normal",
    "log_std_min": -5.0,
    "action_clip_eps": 0.0,
    "actor_lr_schedule": "constant",
    "actor_lr_decay_steps": 1_000_000,
    "actor_dropout": 0.0,
    "source": "torchrl sota-implementations/iql/offline_config.yaml (states not normalized, as there)",
}

#: IQL's actor and data handling as its authors ran them (Kostrikov et al., 2022, the code released
#: with the paper), each with the reason it matters on data whose actions sit at the box's edge.
IQL_AUTHORS_ACTOR: dict[str, Any] = {
    # A Gaussian whose mean is tanh(MLP(s)) and whose samples are left unsquashed, with a learned
    # state-independent log std clipped below at -5. A tanh-squashed Gaussian (TorchRL's recipe) must
    # push its pre-tanh mean towards infinity to give an action of exactly +-1 any likelihood; this
    # actor reaches +-1 with a finite mean.
    "actor": "tanh_mean_gaussian",
    "log_std_min": -5.0,
    # Dataset actions are clipped to +-(1 - 1e-5) of the box before training, as the authors' loader does.
    "action_clip_eps": 1e-5,
    # The actor's learning rate follows a cosine decay to 0 over 1M steps, the authors' budget, whatever
    # the run's length (so it barely moves in a short run); the critics' stays constant.
    "actor_lr_schedule": "cosine",
    "actor_lr_decay_steps": 1_000_000,
    "source": "IQL authors' code: tanh-mean Gaussian actor, state-independent std, actions clipped to "
              "+-(1 - 1e-5), cosine actor lr over 1M steps; raw states (not normalized), as theirs; TorchRL's IQLLoss",
}

#: Adroit: the IQL authors' "kitchen and adroit" config (expectile 0.7, temperature 0.5, dropout 0.1 in
#: the actor's hidden layers, rewards as recorded), with their actor (the Adroit sets' actions sit at
#: +-1 on 5.6-26 % of entries) and normalized states. TD3+BC and BC keep their locomotion settings.
ADROIT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    method: {"expectile": 0.7, "temperature": 0.5, "actor_dropout": 0.1, **IQL_AUTHORS_ACTOR}
    for method in ("iql", "iql_latent")
}
# States normalized, as on mazes: with raw states, as the authors, IQL scored near 0 on hammer- and
# relocate-expert 10k where BC reaches the expert (benchmarks/results/iql_raw_states, seed 0).
ADROIT_HYPERPARAMETERS["iql"].update(normalize_observations=True, source=(
    "IQL authors' code for Adroit (their kitchen/adroit config and actor), with states normalized (theirs are raw)"))

#: Each baseline's hyperparameters; ``train_baseline(..., hyperparameters=...)`` overrides entries.
HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "iql": dict(_IQL),
    "iql_latent": {
        **_IQL,
        "source": "as iql, on TS-IDM latents phi_s(s) (TELS paper Fig. 4 left, App. D.1); "
        "the encoder normalizes states itself",
    },
    "td3bc": {
        "hidden_sizes": [256, 256],
        "activation": "relu",
        "lr": 3e-4,
        "adam_eps": 1e-4,
        "weight_decay": 0.0,
        "alpha": 2.5,
        "policy_noise": 0.2,
        "noise_clip": 0.5,
        "policy_update_delay": 2,
        "gamma": 0.99,
        "tau": 0.005,
        "loss_function": "l2",
        "normalize_observations": True,
        "reward_scale": 1.0,
        "reward_bias": 0.0,
        "source": "torchrl sota-implementations/td3_bc/config.yaml; state normalization "
        "(mean/std + 1e-3) from the TD3+BC paper",
    },
    "bc": {
        "hidden_sizes": [256, 256],
        "activation": "relu",
        "lr": 3e-4,
        "loss_function": "l2",
        "normalize_observations": True,
        "source": "TD3+BC's actor, normalization and optimizer without the Q term; torchrl BCLoss (MSE)",
    },
}

#: Overrides for maze tasks (AntMaze, PointMaze): the IQL paper's AntMaze values
#: (Kostrikov et al., 2022, App. B: expectile 0.9, temperature 10, rewards r - 1),
#: which POR and the TELS paper's maze runs also use.
MAZE_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    method: {"expectile": 0.9, "temperature": 10.0, "reward_bias": -1.0, **IQL_AUTHORS_ACTOR}
    for method in ("iql", "iql_latent")
}
# One departure from the authors on mazes: states normalized (mean/std + 1e-3, as BC and TD3+BC here). The
# authors feed raw states for 1M steps; at the grid's 5k, raw states left IQL near 0 on antmaze-umaze 10k and
# normalized ones near BC (benchmarks/results/iql_raw_states against iql, 3 seeds each; study/REPORT.md, AntMaze).
# TD3+BC on mazes trains on r - 1, the AntMaze convention of IQL and POR (the TD3+BC paper ran no maze): its
# Q term's weight alpha / mean|Q| is large while Q sits near 0 on 0/1 rewards, and on antmaze-umaze 10k it scored
# near 0 with rewards as recorded and far above with r - 1 (benchmarks/results/td3bc_reward_as_recorded, 3 seeds each).
MAZE_HYPERPARAMETERS["td3bc"] = {"reward_bias": -1.0, "source": (
    "torchrl sota-implementations/td3_bc/config.yaml; state normalization (mean/std + 1e-3) from the TD3+BC paper; "
    "rewards r - 1 on mazes, as IQL and POR train AntMaze")}
MAZE_HYPERPARAMETERS["iql"].update(normalize_observations=True, source=(
    "IQL authors' code for AntMaze (tanh-mean Gaussian actor, state-independent std, actions clipped to "
    "+-(1 - 1e-5), cosine actor lr over 1M steps), with states normalized (theirs are raw); TorchRL's IQLLoss"))

_OBS_NORM_EPS = 1e-3  # TD3+BC paper: std + 1e-3


def return_range_scale(data: TensorDictBase) -> float:
    """The IQL paper's locomotion reward scale, ``1000 / (max R - min R)`` over the undiscounted returns R of
    the dataset's episodes (its ``"episode"`` ids; a trailing partial episode counts as one).

    Pieces of a single transition are left out: they are not trajectories, and a one-step "return" near 0
    would set the minimum (the shared halfcheetah 10k file splits each episode into 998 steps and 1 step,
    where D4RL's own q-learning view has whole episodes).
    """
    if "episode" not in data.keys():
        raise ValueError("reward_scale='return_range' needs the dataset's 'episode' ids, and this data has none.")
    episode = data["episode"].reshape(-1).long()
    ids, lengths = episode.unique(return_counts=True)
    returns = torch.zeros(int(episode.max()) + 1, dtype=torch.float64).index_add_(
        0, episode, data["next", "reward"].reshape(-1).double())[ids[lengths > 1]]
    spread = float(returns.max() - returns.min()) if len(returns) else 0.0
    if not spread > 0:
        raise ValueError(f"reward_scale='return_range' needs episodes with different returns; got {len(returns)} "
                         "episode(s) of more than one transition, all with one return.")
    return 1000.0 / spread


def check_reward_scale(setting: Any, reward_bias: float = 0.0) -> None:
    """Raises ``ValueError`` unless ``setting`` is a finite positive number or ``"return_range"``, applied
    without a reward bias (the IQL paper rescales locomotion rewards and shifts AntMaze ones, never both)."""
    number = isinstance(setting, (int, float)) and not isinstance(setting, bool)
    if not (setting == "return_range" or (number and math.isfinite(setting) and setting > 0)):
        raise ValueError(f"reward_scale must be a finite positive number or 'return_range', got {setting!r}.")
    if setting != 1 and reward_bias:
        raise ValueError(f"reward_scale={setting!r} with reward_bias={reward_bias}: the IQL paper rescales "
                         "locomotion rewards and shifts maze rewards by -1, never both; set one.")


def _scale_rewards(data: TensorDictBase, hp: dict[str, Any]) -> tuple[TensorDictBase, float]:
    """Rewards as the baseline trains on them, ``r * reward_scale + reward_bias``, and the scale used."""
    setting, bias = hp.get("reward_scale", 1.0), hp.get("reward_bias", 0.0)
    check_reward_scale(setting, bias)
    scale = return_range_scale(data) if setting == "return_range" else float(setting)
    if scale == 1.0 and not bias:
        return data, scale
    data = data.clone()
    data["next", "reward"] = data["next", "reward"] * scale + bias
    return data, scale


def _clip_actions(data: TensorDictBase, action_spec, eps: float) -> TensorDictBase:
    """The data with its actions clipped to the action box shrunk by ``eps`` of its half-width (IQL's
    authors: +-(1 - 1e-5)), so no action sits exactly on the edge; ``eps=0`` leaves the data as it is."""
    if not eps:
        return data
    low, high = action_spec.space.low.to(data["action"]), action_spec.space.high.to(data["action"])
    center, half = (high + low) / 2, (high - low) / 2 * (1 - eps)
    data = data.clone()
    data["action"] = data["action"].clamp(center - half, center + half)
    return data


def _mlp(in_features: int, out_features: int, hidden_sizes, dropout: float = 0.0) -> MLP:
    return MLP(in_features=in_features, out_features=out_features, num_cells=list(hidden_sizes),
               activation_class=nn.ReLU, dropout=dropout or None)


def _deterministic_actor(obs_key: str, obs_dim: int, action_spec, hp) -> TensorDictSequential:
    """TD3+BC's actor (also BC's): an MLP whose output is squashed into the action box by TanhModule."""
    return TensorDictSequential(
        TensorDictModule(_mlp(obs_dim, action_spec.shape[-1], hp["hidden_sizes"]), in_keys=[obs_key],
                         out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=action_spec),
    )


IQL_ACTORS = ("tanh_normal", "tanh_mean_gaussian")


def _tanh_normal_actor(obs_key, obs_dim, action_spec, hp) -> ProbabilisticActor:
    """TorchRL's IQL recipe actor: a TanhNormal with a state-dependent scale."""
    actor_net = nn.Sequential(
        _mlp(obs_dim, 2 * action_spec.shape[-1], hp["hidden_sizes"], dropout=hp["actor_dropout"]),
        NormalParamExtractor(scale_mapping=f"biased_softplus_{hp['default_policy_scale']}",
                             scale_lb=hp["scale_lb"]),
    )
    return ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[obs_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False},
        default_interaction_type=ExplorationType.RANDOM,
    )


def _tanh_mean_gaussian_actor(obs_key, obs_dim, action_spec, hp) -> ProbabilisticActor:
    """IQL's authors' actor: N(tanh(MLP(s)) mapped into the action box, exp(log_std)), log_std a free
    per-dimension parameter clipped below at ``log_std_min``; samples are not squashed, and the
    deterministic action is the mean, inside the box by construction."""
    act_dim = action_spec.shape[-1]
    return ProbabilisticActor(
        TensorDictSequential(
            TensorDictModule(_mlp(obs_dim, act_dim, hp["hidden_sizes"], dropout=hp["actor_dropout"]),
                             in_keys=[obs_key], out_keys=["mean_param"]),
            TanhModule(in_keys=["mean_param"], out_keys=["loc"], spec=action_spec),
            TensorDictModule(AddStateIndependentNormalScale(act_dim, scale_mapping="exp",
                                                            scale_lb=math.exp(hp["log_std_min"])),
                             in_keys=["loc"], out_keys=["loc", "scale"]),
        ),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=IndependentNormal,
        default_interaction_type=ExplorationType.RANDOM,
    )


def cosine_decay(optimizer: torch.optim.Optimizer, horizon: int) -> torch.optim.lr_scheduler.LambdaLR:
    """The learning rate times ``(1 + cos(pi * min(t, horizon) / horizon)) / 2`` after ``t`` steps: optax's
    ``cosine_decay_schedule``, which IQL's authors apply to the actor over their 1M-step budget."""
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda t: 0.5 * (1 + math.cos(math.pi * min(t, horizon) / horizon)))


def _build_iql(obs_key, obs_dim, action_spec, hp):
    if hp["actor"] not in IQL_ACTORS:
        raise ValueError(f"unknown IQL actor {hp['actor']!r}; expected one of {IQL_ACTORS}.")
    if hp["actor_lr_schedule"] not in ("constant", "cosine"):
        raise ValueError(f"actor_lr_schedule must be 'constant' or 'cosine', got {hp['actor_lr_schedule']!r}.")
    build_actor = _tanh_normal_actor if hp["actor"] == "tanh_normal" else _tanh_mean_gaussian_actor
    actor = build_actor(obs_key, obs_dim, action_spec, hp)
    qvalue = ValueOperator(_mlp(obs_dim + action_spec.shape[-1], 1, hp["hidden_sizes"]), in_keys=[obs_key, "action"])
    value = ValueOperator(_mlp(obs_dim, 1, hp["hidden_sizes"]), in_keys=[obs_key])
    loss = IQLLoss(actor, qvalue, value_network=value, loss_function=hp["loss_function"],
                   temperature=hp["temperature"], expectile=hp["expectile"])
    loss.make_value_estimator(gamma=hp["gamma"])
    target = SoftUpdate(loss, tau=hp["tau"])
    # Separate Adam states per network are what one Adam over all of them computes (Adam is per parameter);
    # the split lets the actor's learning rate follow its own schedule.
    kwargs = {"lr": hp["lr"], "weight_decay": hp["weight_decay"]}
    actor_optim = torch.optim.Adam(list(loss.actor_network_params.values(True, True)), **kwargs)
    critic_optim = torch.optim.Adam([p for group in (loss.qvalue_network_params, loss.value_network_params)
                                     for p in group.values(True, True)], **kwargs)
    schedule = cosine_decay(actor_optim, hp["actor_lr_decay_steps"]) if hp["actor_lr_schedule"] == "cosine" else None

    def update(batch, step):
        losses = loss(batch)
        actor_optim.zero_grad(set_to_none=True)
        critic_optim.zero_grad(set_to_none=True)
        (losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_value"]).backward()
        actor_optim.step()
        critic_optim.step()
        if schedule is not None:
            schedule.step()
        target.step()
        return losses

    return actor, update, loss


def _build_td3bc(obs_key, obs_dim, action_spec, hp):
    actor = _deterministic_actor(obs_key, obs_dim, action_spec, hp)
    qvalue = ValueOperator(_mlp(obs_dim + action_spec.shape[-1], 1, hp["hidden_sizes"]),
                           in_keys=["action", obs_key])
    loss = TD3BCLoss(actor, qvalue, num_qvalue_nets=2, loss_function=hp["loss_function"], delay_actor=True,
                     delay_qvalue=True, action_spec=action_spec, policy_noise=hp["policy_noise"],
                     noise_clip=hp["noise_clip"], alpha=hp["alpha"])
    loss.make_value_estimator(gamma=hp["gamma"])
    target = SoftUpdate(loss, tau=hp["tau"])
    kwargs = {"lr": hp["lr"], "eps": hp["adam_eps"], "weight_decay": hp["weight_decay"]}
    critic_optim = torch.optim.Adam(list(loss.qvalue_network_params.values(True, True)), **kwargs)
    actor_optim = torch.optim.Adam(list(loss.actor_network_params.values(True, True)), **kwargs)

    last_actor_loss = {}

    def update(batch, step):
        # TorchRL's td3_bc script: the critic every step; the actor and both targets every `delay` steps.
        q_loss, _ = loss.qvalue_loss(batch)
        critic_optim.zero_grad(set_to_none=True)
        q_loss.backward()
        critic_optim.step()
        if step % hp["policy_update_delay"] == 0:
            actor_loss, _ = loss.actor_loss(batch)
            actor_optim.zero_grad(set_to_none=True)
            actor_loss.backward()
            actor_optim.step()
            target.step()
            last_actor_loss["value"] = actor_loss.detach()
        # Every step reports both terms (the NaN watch stacks a fixed set): the actor's from its latest update.
        return TensorDict({"loss_qvalue": q_loss, "loss_actor": last_actor_loss["value"]}, [])

    return actor, update, loss


def _build_bc(obs_key, obs_dim, action_spec, hp):
    actor = _deterministic_actor(obs_key, obs_dim, action_spec, hp)
    loss = BCLoss(actor, loss_function=hp["loss_function"])
    optim = torch.optim.Adam(loss.parameters(), lr=hp["lr"])

    def update(batch, step):
        losses = loss(batch)
        optim.zero_grad(set_to_none=True)
        losses["loss_bc"].backward()
        optim.step()
        return losses

    return actor, update, loss


_BUILDERS = {"iql": _build_iql, "iql_latent": _build_iql, "td3bc": _build_td3bc, "bc": _build_bc}


def train_baseline(
    method: str,
    dataset: str | TensorDictBase,
    *,
    steps: int,
    task: str | None = None,
    seed: int = 0,
    batch_size: int = 256,
    eval_interval: int = 5000,
    eval_episodes: int = 10,
    eval_last_n: int = 10,
    eval_max_steps: int = 1000,
    eval_batched: bool = True,
    threads: int | None = None,
    device: str = "auto",
    tsidm_path: str | Path | None = None,
    hyperparameters: Mapping[str, Any] | None = None,
    log_fn: Callable[[Mapping[str, float], int], None] | None = None,
    progress: bool = True,
    return_policy: bool = False,
    return_loss: bool = False,
) -> dict | tuple:
    """Trains one TorchRL baseline on ``dataset`` for ``steps`` gradient steps and evaluates it.

    Args:
        method: ``"iql"``, ``"td3bc"``, ``"bc"`` or ``"iql_latent"``.
        dataset: a dataset name for :func:`~torchrl_tels.data.load_dataset`
            (e.g. ``"hopper-medium-v2-10k"``); its task gives the evaluation env
            and the D4RL reference returns. Or transitions already loaded
            (e.g. after :func:`~torchrl_tels.data.delete_regions`), with ``task``.

    Keyword Args:
        steps: gradient steps (one batch each; for TD3+BC, critic steps).
        task: the evaluation task's name; defaults to the dataset's.
        seed: seeds torch, the replay buffer's sampler and the evaluation episodes.
        batch_size: transitions per step (256, as the recipe).
        eval_interval, eval_episodes, eval_last_n, eval_max_steps: the
            evaluation protocol, as the recipe's ``eval.*``.
        eval_batched: run each evaluation's episodes as one batch of envs, as the recipe's
            ``eval.batched`` (the same episodes up to float rounding; see
            :func:`~torchrl_tels.envs.rollout_episodes`).
        threads: torch intra-op threads; ``None`` keeps torch's setting.
        device: ``auto`` (CUDA where available), ``cpu``, ``cuda`` or ``cuda:N``: the networks and
            the replay buffer live there; evaluation envs run on the CPU.
        tsidm_path: the TS-IDM file (``tsidm.pt`` of a TELS run) for ``iql_latent``.
        hyperparameters: overrides of :data:`HYPERPARAMETERS` ``[method]``.
        log_fn: called with ``({"eval/normalized_score": ..., ...}, step)`` after each evaluation.
        progress: print one line per evaluation.
        return_policy: also return the trained actor and the evaluation env
            (with the observation transforms the actor expects).
        return_loss: also return the trained loss module (with its networks' parameters).

    Returns:
        A dict like the recipe's ``results.json``: ``final_normalized_score_mean``/``_std``
        (over the last ``eval_last_n`` evaluations), ``evaluations``, ``wall_time_s``,
        ``steps_per_s`` (``policy_excluding_eval`` leaves evaluation out), the
        hyperparameters and the budget; for IQL, ``reward_scale_applied``, the factor
        ``reward_scale`` came to. With ``return_policy``, ``(results, actor, env)``; ``return_loss`` appends
        the trained loss module (its critics, for readings of IQL's Q or V).
    """
    if method not in _BUILDERS:
        raise ValueError(f"unknown baseline {method!r}; expected one of {', '.join(METHODS)}.")
    if steps < 1 or eval_interval < 1 or eval_episodes < 1 or eval_last_n < 1:
        raise ValueError("steps, eval_interval, eval_episodes and eval_last_n must be positive.")
    unknown = set(hyperparameters or {}) - set(HYPERPARAMETERS[method])
    if unknown:
        raise ValueError(f"unknown {method} hyperparameter(s) {sorted(unknown)}.")
    hp = {**copy.deepcopy(HYPERPARAMETERS[method]), **dict(hyperparameters or {})}
    device = resolve_device(device)
    if threads:
        torch.set_num_threads(int(threads))
    start_time = time.perf_counter()
    torch.manual_seed(seed)

    if isinstance(dataset, TensorDictBase):
        if task is None:
            raise ValueError("train_baseline: give task= with a dataset passed as a TensorDict.")
        data, dataset = dataset, f"<{len(dataset)} transitions>"
    else:
        data = load_dataset(dataset)
    task = get_task(task or Path(str(dataset)).stem)
    data, reward_scale = _scale_rewards(data, hp)
    obs_dim = data["observation"].shape[-1]
    extra: dict[str, Any] = {"reward_scale_applied": reward_scale} if "reward_scale" in hp else {}

    if method == "iql_latent":
        if tsidm_path is None:
            raise ValueError("iql_latent needs tsidm_path, the TS-IDM file of a TELS run (run_dir/tsidm.pt).")
        tsidm_path = Path(tsidm_path)
        encoder = TSIDMEncoderTransform.from_checkpoint(tsidm_path, observation_dim=obs_dim)
        obs_key, net_in_dim = "latent", encoder.latent_state_dim
        # Write time: the dataset is encoded once; the env encodes each observation with a clone.
        write_transforms = [encoder]
        wrap = lambda env: TransformedEnv(env, encoder.clone())
        extra["tsidm"] = {"path": str(tsidm_path), "sha256": file_sha256(tsidm_path),
                          "latent_state_dim": encoder.latent_state_dim}
    elif hp["normalize_observations"]:
        obs = data["observation"]
        loc, scale = obs.mean(0), obs.std(0) + _OBS_NORM_EPS
        obs_key, net_in_dim = "observation", obs_dim
        write_transforms = [ObservationNorm(loc=loc, scale=scale, in_keys=["observation", ("next", "observation")],
                                            standard_normal=True)]
        wrap = lambda env: TransformedEnv(env, Compose(DoubleToFloat(), ObservationNorm(
            loc=loc.clone(), scale=scale.clone(), in_keys=["observation"], standard_normal=True)))
    else:
        obs_key, net_in_dim = "observation", obs_dim
        write_transforms = []
        wrap = lambda env: TransformedEnv(env, DoubleToFloat())
    env = make_eval_envs(task.env_id, eval_episodes if eval_batched else 1, wrap=wrap, info_keys=task.info_keys)
    action_spec = env.action_spec_unbatched
    data = _clip_actions(data, action_spec, hp.get("action_clip_eps", 0.0))

    buffer = make_offline_replay_buffer(data, batch_size, write_transforms=write_transforms, seed=seed,
                                        device=device)
    with device:  # every network and optimizer state is created there
        actor, update, loss = _BUILDERS[method](obs_key, net_in_dim, action_spec.to(device), hp)
    watch = FiniteWatch({"iql": "IQL", "iql_latent": "IQL", "td3bc": "TD3+BC", "bc": "BC"}[method])
    setup_s = time.perf_counter() - start_time

    evaluations = []
    eval_s = 0.0
    loop_start = time.perf_counter()
    for step in range(steps):
        watch.update(update(buffer.sample(), step), step)
        if (step + 1) % eval_interval == 0 or step + 1 == steps:
            watch.check()  # a non-finite loss is caught here, named with its step, without a sync per step
            eval_start = time.perf_counter()
            actor.eval()
            episodes = evaluate_episodes(actor, env, eval_episodes, max_steps=eval_max_steps,
                                         seed=seed * 100_000 + (step + 1), success_steps=task.success_steps)
            actor.train()
            returns = [e["return"] for e in episodes]
            scores = [normalized_score(task, r) for r in returns]
            evaluations.append({"step": step + 1, "returns": returns, "scores": scores,
                                "score": sum(scores) / len(scores),
                                **success_rate([e["success"] for e in episodes])})
            eval_s += time.perf_counter() - eval_start
            if log_fn is not None:
                log_fn({"eval/return": sum(returns) / len(returns),
                        "eval/normalized_score": evaluations[-1]["score"]}, step + 1)
            if progress:
                print(f"[{method} {task.name} seed {seed}] step {step + 1}/{steps}: normalized score "
                      f"{evaluations[-1]['score']:.1f}", flush=True)
    policy_s = time.perf_counter() - loop_start

    last = torch.tensor([e["score"] for e in evaluations[-eval_last_n:]], dtype=torch.float64)
    results = {
        "method": method,
        "dataset": str(dataset),
        "task": task.name,
        "env": task.env_id,
        "seed": seed,
        "final_normalized_score_mean": last.mean().item(),
        "final_normalized_score_std": last.std(unbiased=False).item(),
        "final_over_last_n_evaluations": len(last),
        "final_success_rate_mean": final_success_rate(evaluations[-eval_last_n:]),
        "evaluations": evaluations,
        "wall_time_s": {"setup": setup_s, "policy": policy_s, "eval": eval_s,
                        "total": time.perf_counter() - start_time},
        "steps_per_s": {
            "policy_including_eval": steps / policy_s,
            "policy_excluding_eval": steps / max(policy_s - eval_s, 1e-9),
        },
        "torch_threads": torch.get_num_threads(),
        "budget": {"policy_steps": steps, "batch_size": batch_size, "eval_interval": eval_interval,
                   "eval_episodes": eval_episodes, "eval_last_n": eval_last_n, "eval_max_steps": eval_max_steps,
                   "evaluations": len(evaluations), "epochs": steps * batch_size / len(data)},
        "hyperparameters": hp,
        **extra,
    }
    out = ((results, actor, env) if return_policy else (results,)) + ((loss,) if return_loss else ())
    return out if len(out) > 1 else results
