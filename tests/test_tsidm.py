"""TS-IDM and TSIDMLoss: Eq. (3)-(7) against independent computations."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch.autograd.functional import jacobian

from torchrl_tels.modules import jvp, TSIDM
from torchrl_tels.objectives import TSIDM_ABLATIONS, TSIDMLoss

OBS, ACT = 5, 2
SMALL = dict(
    encoder_cells=(16, 12),
    decoder_cells=(12, 16),
    inverse_cells=(20, 20),
    action_decoder_cells=(16, 16),
    dynamics_cells=(12, 12),
)


def small_tsidm(dtype=torch.float64, dropout=None, **kwargs) -> TSIDM:
    tsidm = TSIDM(OBS, ACT, inverse_dropout=dropout, **SMALL, **kwargs).to(dtype)
    tsidm.set_state_normalization(torch.randn(OBS), torch.rand(OBS) + 0.5)
    return tsidm


def batch(n=6, dtype=torch.float64, obs=OBS, act=ACT) -> TensorDict:
    return TensorDict(
        {
            "observation": torch.randn(n, obs, dtype=dtype),
            "action": torch.randn(n, act, dtype=dtype),
            ("next", "observation"): torch.randn(n, obs, dtype=dtype),
        },
        [n],
    )


def per_sample_jvp(function, x, v):
    """J_f(x_i) v_i for each row i, from the full Jacobian (the independent reference)."""
    return torch.stack([jacobian(function, x[i]) @ v[i] for i in range(x.shape[0])])


def test_jvp_equals_jacobian_product_float64():
    tsidm = small_tsidm()
    x, v = torch.randn(7, OBS, dtype=torch.float64), torch.randn(7, OBS, dtype=torch.float64)
    y, jv = jvp(tsidm.state_encoder, x, v)
    torch.testing.assert_close(y, tsidm.state_encoder(x), rtol=0, atol=1e-12)
    torch.testing.assert_close(jv, per_sample_jvp(tsidm.state_encoder, x, v), rtol=0, atol=1e-8)
    z, w = torch.randn(7, OBS, dtype=torch.float64), torch.randn(7, OBS, dtype=torch.float64)
    _, jw = jvp(tsidm.state_decoder, z, w)
    torch.testing.assert_close(jw, per_sample_jvp(tsidm.state_decoder, z, w), rtol=0, atol=1e-8)


def test_generic_modules_fall_back_to_forward_mode_autodiff():
    net = torch.nn.Sequential(torch.nn.Linear(OBS, 7), torch.nn.Tanh(), torch.nn.Linear(7, 3)).double()
    x, v = torch.randn(4, OBS, dtype=torch.float64), torch.randn(4, OBS, dtype=torch.float64)
    _, jv = jvp(net, x, v)
    torch.testing.assert_close(jv, per_sample_jvp(net, x, v), rtol=0, atol=1e-8)


def reference_terms(tsidm: TSIDM, td: TensorDict) -> dict[str, torch.Tensor]:
    """Eq. (3)-(6) written out with explicit Jacobians, independently of TSIDMLoss."""
    s = (td["observation"] - tsidm.obs_loc) / tsidm.obs_scale
    s_next = (td["next", "observation"] - tsidm.obs_loc) / tsidm.obs_scale
    s_dot = s_next - s
    phi, psi = tsidm.state_encoder, tsidm.state_decoder
    z, z_next = phi(s), phi(s_next)
    z_a = tsidm.inverse_dynamics(torch.cat([z, z_next], -1))
    fwd = tsidm.forward_dynamics(torch.cat([z, z_a], -1))
    rvs = tsidm.reverse_dynamics(torch.cat([z_next, z_a], -1))
    rec = ((psi(z) - s) ** 2).sum(-1) + ((tsidm.action_decoder(z_a) - td["action"]) ** 2).sum(-1)
    dyn = ((per_sample_jvp(phi, s, s_dot) - fwd) ** 2).sum(-1) + (
        (per_sample_jvp(phi, s_next, -s_dot) - rvs) ** 2
    ).sum(-1)
    ode = ((per_sample_jvp(psi, z, fwd) - s_dot) ** 2).sum(-1) + (
        (per_sample_jvp(psi, z_next, rvs) + s_dot) ** 2
    ).sum(-1)
    rvs_at_predicted = tsidm.reverse_dynamics(torch.cat([z + fwd, z_a], -1))
    tsym = ((fwd + rvs_at_predicted) ** 2).sum(-1)
    return {"rec": rec.mean(), "dyn": dyn.mean(), "ode": ode.mean(), "tsym": tsym.mean()}


@pytest.mark.parametrize("beta", [1.0, 0.1])
def test_loss_terms_match_explicit_jacobians(beta):
    tsidm = small_tsidm()
    td = batch()
    out = TSIDMLoss(tsidm, beta=beta)(td)
    with torch.no_grad():
        ref = reference_terms(tsidm, td)
    for name in ("rec", "dyn", "ode", "tsym"):
        torch.testing.assert_close(out[f"ell_{name}"], ref[name], rtol=0, atol=1e-8)
    for name in ("dyn", "ode", "tsym"):
        torch.testing.assert_close(out[f"loss_{name}"], beta * ref[name], rtol=0, atol=1e-8)
    # Eq. (7): the loss_* entries sum to l_rec + beta (l_dyn + l_ode + l_Tsym).
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    expected = ref["rec"] + beta * (ref["dyn"] + ref["ode"] + ref["tsym"])
    torch.testing.assert_close(total, expected, rtol=0, atol=1e-8)
    torch.testing.assert_close(out["ell_total"], expected, rtol=0, atol=1e-8)
    # What beta candidates are compared on: the same four terms, without beta.
    unweighted = ref["rec"] + ref["dyn"] + ref["ode"] + ref["tsym"]
    torch.testing.assert_close(out["ell_sum"], unweighted, rtol=0, atol=1e-8)


def test_term_weights_scale_each_regularizer_inside_beta():
    tsidm = small_tsidm()
    td = batch()
    weights = {"dyn": 0.1, "tsym": 0.25}  # TSRL-like; ode keeps weight 1
    out = TSIDMLoss(tsidm, beta=0.5, term_weights=weights)(td)
    with torch.no_grad():
        ref = reference_terms(tsidm, td)
    expected = {"dyn": 0.5 * 0.1 * ref["dyn"], "ode": 0.5 * ref["ode"], "tsym": 0.5 * 0.25 * ref["tsym"]}
    for name, value in expected.items():
        torch.testing.assert_close(out[f"loss_{name}"], value, rtol=0, atol=1e-8)
        torch.testing.assert_close(out[f"ell_{name}"], ref[name], rtol=0, atol=1e-8)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    torch.testing.assert_close(total, ref["rec"] + sum(expected.values()), rtol=0, atol=1e-8)
    torch.testing.assert_close(out["ell_total"], total.detach(), rtol=0, atol=1e-8)


def test_jvp_terms_are_differentiable_like_explicit_jacobians():
    """Gradients of ℓ_dyn + ℓ_ode through the JVPs equal those through explicit Jacobians."""
    tsidm = small_tsidm()
    td = batch(n=3)
    out = TSIDMLoss(tsidm, beta=1.0)(td)
    (out["loss_dyn"] + out["loss_ode"]).backward()
    zeros = torch.zeros_like
    grads = {n: zeros(p) if p.grad is None else p.grad.clone() for n, p in tsidm.named_parameters()}
    tsidm.zero_grad()

    def explicit(tsidm):
        s = (td["observation"] - tsidm.obs_loc) / tsidm.obs_scale
        s_next = (td["next", "observation"] - tsidm.obs_loc) / tsidm.obs_scale
        s_dot = s_next - s
        phi, psi = tsidm.state_encoder, tsidm.state_decoder
        total = 0.0
        for i in range(s.shape[0]):
            j_s = jacobian(phi, s[i], create_graph=True)
            j_sn = jacobian(phi, s_next[i], create_graph=True)
            z, zn = phi(s[i]), phi(s_next[i])
            za = tsidm.inverse_dynamics(torch.cat([z, zn]))
            fwd = tsidm.forward_dynamics(torch.cat([z, za]))
            rvs = tsidm.reverse_dynamics(torch.cat([zn, za]))
            jz = jacobian(psi, z, create_graph=True)
            jzn = jacobian(psi, zn, create_graph=True)
            total = total + ((j_s @ s_dot[i] - fwd) ** 2).sum() + ((j_sn @ -s_dot[i] - rvs) ** 2).sum()
            total = total + ((jz @ fwd - s_dot[i]) ** 2).sum() + ((jzn @ rvs + s_dot[i]) ** 2).sum()
        return total / s.shape[0]

    explicit(tsidm).backward()
    for name, p in tsidm.named_parameters():
        explicit_grad = zeros(p) if p.grad is None else p.grad
        torch.testing.assert_close(explicit_grad, grads[name], rtol=1e-7, atol=1e-9, msg=name)
    assert grads["state_encoder.0.weight"].abs().sum() > 0


def test_tsym_is_zero_for_exact_time_reversal_and_positive_otherwise():
    tsidm = small_tsidm()
    fwd, rvs = tsidm.forward_dynamics, tsidm.reverse_dynamics
    z_size = tsidm.latent_state_dim
    with torch.no_grad():
        # h_fwd depends on z_a only, and h_rvs is its exact negation: then
        # h_rvs(z + h_fwd(z, z_a), z_a) = -h_fwd(z, z_a) for every z.
        fwd[0].weight[:, :z_size] = 0.0
        for layer_f, layer_r in zip(fwd, rvs):
            if isinstance(layer_f, torch.nn.Linear):
                layer_r.weight.copy_(layer_f.weight)
                layer_r.bias.copy_(layer_f.bias)
        rvs[-1].weight.neg_()
        rvs[-1].bias.neg_()
    z = torch.randn(32, z_size, dtype=torch.float64)
    z_a = torch.randn(32, tsidm.latent_action_dim, dtype=torch.float64)
    assert tsidm.latent_forward(z, z_a).abs().mean() > 1e-3  # not trivially zero
    assert tsidm.tsym_consistency(z, z_a).abs().max() < 1e-20
    with torch.no_grad():
        # h_rvs now also depends on z: no longer a time reversal
        rvs[0].weight[:, :z_size] += 0.5 * torch.randn_like(rvs[0].weight[:, :z_size])
    broken = tsidm.tsym_consistency(z, z_a)
    assert broken.mean() > 1e-3
    assert (broken > 1e-12).float().mean() > 0.9


SUBNETS = (
    "state_encoder",
    "state_decoder",
    "inverse_dynamics",
    "action_decoder",
    "forward_dynamics",
    "reverse_dynamics",
)


def test_gradients_reach_every_subnetwork_in_full_variant():
    tsidm = small_tsidm(dropout=0.1)
    out = TSIDMLoss(tsidm)(batch())
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    for name in SUBNETS:
        grad = sum(p.grad.abs().sum() for p in getattr(tsidm, name).parameters())
        assert grad > 0, name


@pytest.mark.parametrize(
    "ablation,terms,untouched",
    [
        ("ae", {"state_rec", "action_rec"}, {"forward_dynamics", "reverse_dynamics"}),
        ("dyn", {"state_rec", "action_rec", "dyn"}, set()),
        ("ode", {"state_rec", "action_rec", "dyn", "ode"}, set()),
        ("full", {"state_rec", "action_rec", "dyn", "ode", "tsym"}, set()),
    ],
)
def test_ablations_drop_exactly_their_terms(ablation, terms, untouched):
    tsidm = small_tsidm()
    td = batch()
    full = TSIDMLoss(tsidm, ablation="full")(td)
    loss = TSIDMLoss(tsidm, ablation=ablation)
    out = loss(td)
    loss_keys = {k[len("loss_"):] for k in out.keys() if k.startswith("loss_")}
    assert loss_keys == terms
    assert set(out.keys()) == set(loss.out_keys)
    for term in terms:  # the kept terms are the same numbers as in the full model
        torch.testing.assert_close(out[f"loss_{term}"], full[f"loss_{term}"])
    sum(out[f"loss_{t}"] for t in terms).backward()
    for name in SUBNETS:
        got_grad = any(
            p.grad is not None and p.grad.abs().sum() > 0 for p in getattr(tsidm, name).parameters()
        )
        assert got_grad == (name not in untouched), name
    assert TSIDM_ABLATIONS == ("ae", "dyn", "ode", "full")


def test_set_keys_renames_inputs():
    tsidm = small_tsidm()
    td = batch()
    loss = TSIDMLoss(tsidm)
    expected = loss(td)
    renamed = TensorDict(
        {"obs": td["observation"], "act": td["action"], ("next", "obs"): td["next", "observation"]},
        td.batch_size,
    )
    loss.set_keys(observation="obs", action="act")
    assert set(loss.in_keys) == {"obs", "act", ("next", "obs")}
    out = loss(renamed)
    torch.testing.assert_close(out["ell_total"], expected["ell_total"])


@pytest.mark.parametrize(
    "mutate,error,pattern",
    [
        (lambda td: td.set("observation", torch.randn(6, OBS + 1, dtype=torch.float64)), ValueError,
         r"'observation' has shape \(6, 6\), expected a trailing dimension of 5"),
        (lambda td: td.set("action", torch.randn(6, ACT + 2, dtype=torch.float64)), ValueError,
         r"'action' has shape \(6, 4\), expected a trailing dimension of 2"),
        (lambda td: td["next"].set("observation", torch.full((6, OBS), float("nan"), dtype=torch.float64)),
         ValueError, r"\('next', 'observation'\).*NaN/inf"),
        (lambda td: td["action"].__setitem__((0, 0), float("inf")), ValueError, r"'action'.*1 NaN/inf"),
        (lambda td: td.exclude("action", inplace=True), KeyError, r"no key 'action'"),
        (lambda td: td.exclude(("next", "observation"), inplace=True), KeyError, r"no key \('next', 'observation'\)"),
    ],
)
def test_bad_batches_raise_clear_errors(mutate, error, pattern):
    td = batch()
    mutate(td)
    with pytest.raises(error, match=pattern):
        TSIDMLoss(small_tsidm())(td)


@pytest.mark.parametrize(
    "kwargs,pattern",
    [
        ({"beta": -1.0}, "beta must be a finite number >= 0"),
        ({"beta": float("nan")}, "beta must be a finite number >= 0"),
        ({"ablation": "nope"}, "unknown ablation 'nope'"),
        ({"dim_reduction": "max"}, "dim_reduction"),
        ({"term_weights": {"rec": 1.0}}, r"unknown term_weights \['rec'\]"),
        ({"term_weights": {"dyn": -0.1}}, r"term_weights\['dyn'\] must be finite and >= 0"),
    ],
)
def test_bad_hyperparameters_raise(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        TSIDMLoss(small_tsidm(), **kwargs)


def test_state_normalization_travels_with_the_state_dict():
    tsidm = small_tsidm()
    copy = TSIDM(**tsidm.config()).double()
    copy.load_state_dict(tsidm.state_dict())
    obs = torch.randn(4, OBS, dtype=torch.float64)
    torch.testing.assert_close(copy.encode_state(obs), tsidm.encode_state(obs))


def test_encode_states_in_chunks_equals_one_pass_and_keeps_leading_dims():
    tsidm = small_tsidm()
    observation = torch.randn(4, 7, OBS)
    whole = tsidm.encode_state(observation).detach()
    chunked = tsidm.encode_states(observation, chunk_size=3)  # 28 rows: chunks of 3, the last of 1
    assert chunked.shape == whole.shape == (4, 7, tsidm.latent_state_dim) and not chunked.requires_grad
    torch.testing.assert_close(chunked, whole, rtol=1e-6, atol=1e-6)
    assert tsidm.encode_states(torch.empty(0, OBS)).shape == (0, tsidm.latent_state_dim)


def test_training_on_hopper_lowers_every_term(hopper_arrays):
    torch.manual_seed(0)
    data = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in hopper_arrays.items()}
    obs, act, next_obs = data["observations"], data["actions"], data["next_observations"]
    tsidm = TSIDM(obs.shape[-1], act.shape[-1], encoder_cells=(128, 128), decoder_cells=(128, 128),
                  inverse_cells=(256, 256), action_decoder_cells=(128, 128), dynamics_cells=(128, 128))
    tsidm.fit_state_normalization(obs)
    loss = TSIDMLoss(tsidm, beta=1.0)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(0)
    history = []
    for _ in range(500):
        idx = torch.randint(obs.shape[0], (256,), generator=generator)
        td = TensorDict({"observation": obs[idx], "action": act[idx], ("next", "observation"): next_obs[idx]}, [256])
        out = loss(td)
        optim.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optim.step()
        history.append({k: out[k].item() for k in ("loss_state_rec", "loss_action_rec", "ell_dyn", "ell_ode", "ell_tsym")})
    for key in history[0]:
        # ℓ_T-sym starts near 0 (both ODE nets output ~0) and first grows with
        # the dynamics targets; over 500 steps every term ends well below its start.
        first = sum(h[key] for h in history[:50]) / 50
        last = sum(h[key] for h in history[-50:]) / 50
        assert last < 0.5 * first, f"{key}: {first:.4g} -> {last:.4g}"
