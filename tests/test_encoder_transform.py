"""TSIDMEncoderTransform: in an env, on replay-buffer samples, at write time, and under a stock IQLLoss."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer, Unbounded
from torchrl.envs import GymEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MLP, NormalParamExtractor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import IQLLoss

from torchrl_tels.checkpoint import CheckpointError
from torchrl_tels.envs import TSIDMEncoderTransform
from torchrl_tels.modules import TSIDM

OBS_DIM, ACTION_DIM, LATENT_DIM = 11, 3, 8  # Hopper-v4; latent != obs size to catch shape mix-ups


def small_tsidm(observation_dim: int = OBS_DIM) -> TSIDM:
    tsidm = TSIDM(
        observation_dim,
        ACTION_DIM,
        latent_state_dim=LATENT_DIM,
        encoder_cells=(32, 32),
        decoder_cells=(32, 32),
        inverse_cells=(32, 32),
        action_decoder_cells=(32, 32),
        dynamics_cells=(32, 32),
    )
    # A non-trivial normalization, so a transform that skipped it would be caught.
    tsidm.set_state_normalization(
        torch.linspace(-1.0, 1.0, observation_dim), torch.linspace(0.5, 2.0, observation_dim)
    )
    return tsidm


def expected_latent(tsidm: TSIDM, observation: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return tsidm.encode_state(observation.float())


def transitions(n: int = 64) -> TensorDict:
    observation = torch.randn(n, OBS_DIM)
    return TensorDict(
        {
            "observation": observation,
            "action": torch.rand(n, ACTION_DIM) * 2 - 1,
            ("next", "observation"): observation + 0.1 * torch.randn(n, OBS_DIM),
            ("next", "reward"): observation[:, :1].clone(),
            ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        },
        batch_size=[n],
    )


def count_encoder_calls(transform: TSIDMEncoderTransform) -> list:
    calls = []
    transform.tsidm.state_encoder.register_forward_hook(lambda module, args, out: calls.append(args[0].shape))
    return calls


# --------------------------------------------------------------------- env
def test_env_specs_reset_and_step_latents():
    tsidm = small_tsidm()
    env = TransformedEnv(GymEnv("Hopper-v4"), TSIDMEncoderTransform(tsidm))
    env.set_seed(0)

    spec = env.observation_spec["latent"]
    assert isinstance(spec, Unbounded)
    assert spec.shape == (LATENT_DIM,) and spec.dtype == torch.float32
    assert "observation" in env.observation_spec.keys()
    check_env_specs(env)

    reset = env.reset()  # Transform._reset is a no-op: the first latent comes from our _reset
    torch.testing.assert_close(reset["latent"], expected_latent(tsidm, reset["observation"]))

    rollout = env.rollout(4)
    torch.testing.assert_close(rollout["latent"], expected_latent(tsidm, rollout["observation"]))
    torch.testing.assert_close(
        rollout["next", "latent"], expected_latent(tsidm, rollout["next", "observation"])
    )
    assert not rollout["next", "latent"].requires_grad


def test_env_drop_observation():
    env = TransformedEnv(GymEnv("Hopper-v4"), TSIDMEncoderTransform(small_tsidm(), keep_observation=False))
    assert "observation" not in env.observation_spec.keys()
    check_env_specs(env)
    rollout = env.rollout(3)
    assert "observation" not in rollout.keys() and ("next", "observation") not in rollout.keys(True)
    assert rollout["next", "latent"].shape == (3, LATENT_DIM)


def test_env_with_tsidm_for_another_env_is_refused():
    env = TransformedEnv(GymEnv("Hopper-v4"), TSIDMEncoderTransform(small_tsidm(observation_dim=17)))
    with pytest.raises(ValueError, match=r"size 11.*size 17"):
        env.observation_spec


def test_clone_shares_weights_and_attaches_to_second_env_and_buffer():
    transform = TSIDMEncoderTransform(small_tsidm())
    env = TransformedEnv(GymEnv("Hopper-v4"), transform)
    # One transform, one parent: reusing the instance must fail loudly...
    with pytest.raises(AttributeError, match="clone"):
        TransformedEnv(GymEnv("Hopper-v4"), transform)
    # ...and a clone works, sharing the frozen weights instead of copying them.
    clone = transform.clone()
    assert clone.tsidm is transform.tsidm
    weight = transform.tsidm.state_encoder[0].weight
    assert clone.tsidm.state_encoder[0].weight.data_ptr() == weight.data_ptr()
    env2 = TransformedEnv(GymEnv("Hopper-v4"), clone)
    check_env_specs(env2)

    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(16), batch_size=4)
    rb.append_transform(transform.clone())
    rb.extend(env.rollout(5))
    sample = rb.sample()
    torch.testing.assert_close(sample["latent"], expected_latent(transform.tsidm, sample["observation"]))


def test_encoder_stays_frozen_in_train_mode():
    tsidm = small_tsidm()
    transform = TSIDMEncoderTransform(tsidm)
    env = TransformedEnv(GymEnv("Hopper-v4"), transform)
    env.train()
    transform.train()
    assert transform.training and not transform.tsidm.training
    assert not any(module.training for module in transform.tsidm.modules())
    assert not any(p.requires_grad for p in transform.tsidm.parameters())
    # The caller's module was copied, not frozen in place.
    assert all(p.requires_grad for p in tsidm.parameters())

    with torch.enable_grad():
        out = transform(TensorDict(observation=torch.randn(5, OBS_DIM, requires_grad=True), batch_size=[5]))
    assert not out["latent"].requires_grad


# ------------------------------------------------------------ replay buffer
def test_sample_time_buffer_encodes_root_and_next():
    tsidm = small_tsidm()
    data = transitions()
    transform = TSIDMEncoderTransform(tsidm)
    calls = count_encoder_calls(transform)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=16, transform=transform)
    rb.extend(data)
    # Encoded when sampled, not when stored.
    assert calls == [] and "latent" not in rb.storage[:].keys()

    sample = rb.sample()
    torch.testing.assert_close(sample["latent"], expected_latent(tsidm, sample["observation"]))
    torch.testing.assert_close(sample["next", "latent"], expected_latent(tsidm, sample["next", "observation"]))
    assert sample["latent"].shape == (16, LATENT_DIM)


def test_write_time_buffer_encodes_once_per_extend():
    tsidm = small_tsidm()
    data = transitions()
    transform = TSIDMEncoderTransform(tsidm, keep_observation=False)
    calls = count_encoder_calls(transform)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=16)
    rb.append_transform(transform, invert=True)
    rb.extend(data)

    # One batched encoder pass for the root observations, one for ("next", ...).
    assert calls == [torch.Size([64, OBS_DIM])] * 2
    stored = rb.storage[:]
    torch.testing.assert_close(stored["latent"], expected_latent(tsidm, data["observation"]))
    torch.testing.assert_close(stored["next", "latent"], expected_latent(tsidm, data["next", "observation"]))
    assert "observation" not in stored.keys() and ("next", "observation") not in stored.keys(True)

    for _ in range(3):
        sample = rb.sample()
    assert len(calls) == 2  # sampling reads the stored latents
    assert sample["next", "latent"].shape == (16, LATENT_DIM)


# --------------------------------------------------------- errors, checkpoints
def test_wrong_observation_size_names_key_and_shape():
    transform = TSIDMEncoderTransform(small_tsidm())
    bad = TensorDict(
        {"observation": torch.zeros(4, OBS_DIM), ("next", "observation"): torch.zeros(4, 7)}, [4]
    )
    with pytest.raises(ValueError, match=r"\('next', 'observation'\).*\(4, 7\).*size 11"):
        transform(bad)
    with pytest.raises(KeyError, match="'observation' not found"):
        transform(TensorDict(obs=torch.zeros(4, OBS_DIM), batch_size=[4]))


def test_from_checkpoint(tmp_path):
    tsidm = small_tsidm()
    path = tmp_path / "tsidm.pt"
    tsidm.save(path)
    obs = torch.randn(6, OBS_DIM)

    for transform in (
        TSIDMEncoderTransform.from_checkpoint(path, observation_dim=OBS_DIM),
        TSIDMEncoderTransform(str(path), in_keys=["pixels"], out_keys=["z"]),
    ):
        key_in, key_out = transform.in_keys[0], transform.out_keys[0]
        out = transform(TensorDict({key_in: obs}, batch_size=[6]))
        torch.testing.assert_close(out[key_out], expected_latent(tsidm, obs))
        assert not transform.tsidm.training

    with pytest.raises(CheckpointError, match="observation_dim=11.*observation_dim=17"):
        TSIDMEncoderTransform.from_checkpoint(path, observation_dim=17)


def test_several_key_pairs():
    tsidm = small_tsidm()
    transform = TSIDMEncoderTransform(tsidm, in_keys=["observation", "goal"])
    assert transform.out_keys == ["observation_latent", "goal_latent"]
    obs, goal = torch.randn(3, OBS_DIM), torch.randn(3, OBS_DIM)
    out = transform(TensorDict(observation=obs, goal=goal, batch_size=[3]))
    torch.testing.assert_close(out["observation_latent"], expected_latent(tsidm, obs))
    torch.testing.assert_close(out["goal_latent"], expected_latent(tsidm, goal))


# ------------------------------------------------------- someone else's loss
@pytest.mark.filterwarnings("ignore:No target network updater")
def test_stock_iql_trains_on_latent_batches():
    transform = TSIDMEncoderTransform(small_tsidm(), keep_observation=False)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(256), batch_size=128)
    rb.append_transform(transform, invert=True)
    rb.extend(transitions(256))
    batch = rb.sample()
    assert "observation" not in batch.keys()  # the loss can only be reading the latents

    actor = ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(
                MLP(in_features=LATENT_DIM, out_features=2 * ACTION_DIM, num_cells=[64, 64]),
                NormalParamExtractor(),
            ),
            in_keys=["latent"],
            out_keys=["loc", "scale"],
        ),
        in_keys=["loc", "scale"],
        spec=Bounded(-1.0, 1.0, (ACTION_DIM,)),
        distribution_class=TanhNormal,
    )

    class QNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = MLP(in_features=LATENT_DIM + ACTION_DIM, out_features=1, num_cells=[64, 64])

        def forward(self, latent, action):
            return self.mlp(torch.cat([latent, action], -1))

    qvalue = ValueOperator(QNet(), in_keys=["latent", "action"])
    value = ValueOperator(MLP(in_features=LATENT_DIM, out_features=1, num_cells=[64, 64]), in_keys=["latent"])
    with torch.no_grad():
        # Start V away from Q so both regressions have a clear distance to close.
        value.module[-1].bias.fill_(3.0)
    loss = IQLLoss(actor, qvalue, value)
    loss.make_value_estimator(gamma=0.99)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-3)

    history = []
    for _ in range(50):
        losses = loss(batch.clone())
        total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_value"]
        optim.zero_grad()
        total.backward()
        optim.step()
        history.append((losses["loss_qvalue"].item(), losses["loss_value"].item()))

    (q_first, v_first), (q_last, v_last) = history[0], history[-1]
    assert q_last < 0.5 * q_first, history
    assert v_last < 0.5 * v_first, history
    assert not any(p.grad is not None and p.grad.abs().sum() > 0 for p in transform.tsidm.parameters())
