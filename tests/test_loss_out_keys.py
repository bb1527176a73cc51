"""select_out_keys, out_keys and out_keys_source on the three TELS losses, as on torchrl's losses."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.objectives import SoftUpdate

from tests.test_latent_policy import CELLS, latent_batch, make_guide_loss, small_tsidm as small_policy_tsidm
from tests.test_tsidm import batch, small_tsidm
from torchrl_tels.errors import OutKeysError, TelsError
from torchrl_tels.modules import make_latent_value
from torchrl_tels.objectives import LatentExpectileLoss, TSIDMLoss, TSymGuideLoss
from torchrl_tels.training import sum_losses

TSIDM_FULL = ["loss_state_rec", "loss_action_rec", "loss_dyn", "loss_ode", "loss_tsym",
              "ell_rec", "ell_dyn", "ell_ode", "ell_tsym", "ell_total", "ell_sum", "latent_rms", "latent_step_rms"]
GUIDE_DETERMINISTIC = ["loss_guide_value", "loss_guide_state", "loss_tsym",
                       "lambda_alpha", "guide_value", "guide_step_rms", "tsym_to_state_ratio"]
GUIDE_STOCHASTIC = ["loss_guide_awr", "loss_tsym", "advantage", "clipped_weight_fraction", "effective_sample_fraction"]


def tsidm_case():
    return TSIDMLoss(small_tsidm(), beta=0.5), batch(), ("loss_state_rec", "loss_dyn", "ell_total")


def expectile_case():
    tsidm = small_policy_tsidm()
    loss = LatentExpectileLoss(make_latent_value(tsidm.latent_state_dim, CELLS), expectile=0.8)
    loss.make_value_estimator(gamma=0.9)
    SoftUpdate(loss, tau=0.05)
    return loss, latent_batch(tsidm), ("value_target", "loss_value")


def guide_case(mode, selected):
    def case():
        tsidm = small_policy_tsidm()
        loss, _, _ = make_guide_loss(mode, tsidm, eta=2.0)
        return loss, latent_batch(tsidm), selected
    return case


CASES = {
    "tsidm": tsidm_case,
    "expectile": expectile_case,
    "guide-deterministic": guide_case("deterministic", ("loss_guide_state", "loss_tsym", "lambda_alpha")),
    "guide-stochastic": guide_case("stochastic", ("loss_tsym", "loss_guide_awr", "advantage")),
}
FULL_OUT_KEYS = {
    "tsidm": TSIDM_FULL,
    "expectile": ["loss_value", "state_value", "value_target"],
    "guide-deterministic": GUIDE_DETERMINISTIC,
    "guide-stochastic": GUIDE_STOCHASTIC,
}


def run(loss, td):
    # the stochastic guide draws its T-symmetry sample with rsample: the same seed, the same draw
    torch.manual_seed(7)
    return loss(td.clone())


def keyword_arguments(loss, td):
    """The keyword call @dispatch accepts: one argument per in_key, nested keys joined by "_"."""
    return {"_".join(key) if isinstance(key, tuple) else key: td.get(key) for key in loss.in_keys}


def loss_gradients(loss, objective):
    params = [p for p in loss.parameters() if p.requires_grad]
    return torch.autograd.grad(objective, params, allow_unused=True)


@pytest.mark.parametrize("name", list(CASES))
def test_selection_keeps_exactly_the_chosen_entries_with_their_values(name):
    loss, td, selected = CASES[name]()
    full = run(loss, td)
    assert loss.out_keys == FULL_OUT_KEYS[name]

    assert loss.select_out_keys(*selected) is loss
    out = run(loss, td)
    assert set(out.keys()) == set(selected)
    assert loss.out_keys == list(selected)
    assert loss.out_keys_source == FULL_OUT_KEYS[name]
    for key in selected:
        torch.testing.assert_close(out[key], full[key], rtol=0, atol=0)


@pytest.mark.parametrize("name", list(CASES))
def test_the_objective_is_the_sum_of_the_selected_loss_terms(name):
    loss, td, selected = CASES[name]()
    full = run(loss, td)
    kept = [key for key in selected if key.startswith("loss_")]
    assert kept
    expected = loss_gradients(loss, sum(full[key] for key in kept))

    loss.select_out_keys(*selected)
    out = run(loss, td)
    torch.testing.assert_close(sum_losses(out), sum(full[key] for key in kept).detach(), rtol=0, atol=0)
    for got, want in zip(loss_gradients(loss, sum_losses(out)), expected):
        assert (got is None) == (want is None)
        if got is not None:
            torch.testing.assert_close(got, want, rtol=0, atol=0)


@pytest.mark.parametrize("name", list(CASES))
def test_keyword_calls_return_the_selected_entries_in_order(name):
    loss, td, selected = CASES[name]()
    full = run(loss, td)
    kwargs = keyword_arguments(loss, td)

    torch.manual_seed(7)
    values = loss(**kwargs)
    assert len(values) == len(FULL_OUT_KEYS[name])
    for key, value in zip(FULL_OUT_KEYS[name], values):
        torch.testing.assert_close(value, full[key], rtol=0, atol=0)

    loss.select_out_keys(*selected)
    torch.manual_seed(7)
    values = loss(**kwargs)
    assert isinstance(values, tuple) and len(values) == len(selected)
    for key, value in zip(selected, values):
        torch.testing.assert_close(value, full[key], rtol=0, atol=0)

    loss.select_out_keys(selected[-1])
    torch.manual_seed(7)
    value = loss(**kwargs)
    assert isinstance(value, torch.Tensor)
    torch.testing.assert_close(value, full[selected[-1]], rtol=0, atol=0)


@pytest.mark.parametrize("name", list(CASES))
def test_reset_restores_the_full_output(name):
    loss, td, selected = CASES[name]()
    loss.select_out_keys(*selected)
    assert loss.reset_out_keys() is loss
    assert loss.out_keys == FULL_OUT_KEYS[name]
    assert set(run(loss, td).keys()) == set(FULL_OUT_KEYS[name])


@pytest.mark.parametrize("name", list(CASES))
def test_an_unknown_key_is_refused_by_name_and_changes_nothing(name):
    loss, td, selected = CASES[name]()
    with pytest.raises(OutKeysError, match=r"cannot select 'loss_nope': not among \['") as info:
        loss.select_out_keys("loss_nope")
    assert isinstance(info.value, TelsError)
    for key in FULL_OUT_KEYS[name]:
        assert repr(key) in str(info.value)
    with pytest.raises(OutKeysError, match="'loss_nope'"):
        loss.select_out_keys(selected[0], "loss_nope")
    with pytest.raises(OutKeysError, match="'loss_nope'"):
        loss.out_keys = [selected[0], "loss_nope"]
    assert loss.out_keys == FULL_OUT_KEYS[name]
    assert set(run(loss, td).keys()) == set(FULL_OUT_KEYS[name])


def test_unknown_keys_raise_what_tensordict_modules_raise():
    """tensordict raises ValueError for one unknown key and RuntimeError for several; both handlers catch ours."""
    module = TensorDictModule(lambda a: (a, a), in_keys=["a"], out_keys=["b", "c"])
    loss, _, _ = tsidm_case()
    for reference_keys, keys in ((("nope",), ("loss_nope",)), (("b", "nope"), ("loss_state_rec", "loss_nope"))):
        with pytest.raises(Exception) as reference:
            module.select_out_keys(*reference_keys)
        with pytest.raises(type(reference.value)):
            loss.select_out_keys(*keys)


def test_keys_passed_as_one_list_get_a_hint():
    loss, _, _ = tsidm_case()
    with pytest.raises(OutKeysError, match=r"separate arguments: select_out_keys\('loss_dyn', 'ell_rec'\)"):
        loss.select_out_keys(["loss_dyn", "ell_rec"])


def test_a_second_selection_chooses_among_the_first():
    loss, td, _ = tsidm_case()
    loss.select_out_keys("loss_state_rec", "loss_action_rec")
    with pytest.raises(OutKeysError, match=r"earlier select_out_keys narrowed them; reset_out_keys\(\) restores"):
        loss.select_out_keys("loss_dyn")
    loss.select_out_keys("loss_action_rec")
    assert set(run(loss, td).keys()) == {"loss_action_rec"}
    assert loss.out_keys_source == TSIDM_FULL


def test_the_out_keys_setter_selects_and_none_restores():
    loss, td, _ = expectile_case()
    loss.out_keys = ["loss_value"]
    assert set(run(loss, td).keys()) == {"loss_value"}
    loss.out_keys = None
    assert set(run(loss, td).keys()) == {"loss_value", "state_value", "value_target"}


def test_selection_holds_when_the_batch_lacks_a_key_the_loss_can_do_without():
    # TD(0) reads "terminated", not "done"; a batch without ("next", "done") must still be filtered
    loss, td, _ = expectile_case()
    del td["next", "done"]
    full = run(loss, td)
    loss.select_out_keys("loss_value")
    out = run(loss, td)
    assert set(out.keys()) == {"loss_value"}
    torch.testing.assert_close(out["loss_value"], full["loss_value"], rtol=0, atol=0)


def test_a_selected_entry_the_options_no_longer_write_is_reported():
    loss, td, _ = guide_case("deterministic", ())()
    loss.select_out_keys("loss_guide_state", "loss_tsym")
    loss.tsym_regularizer = False
    with pytest.raises(OutKeysError, match="'loss_tsym' is no longer written"):
        loss(td)


# ------------------------------------------------------ out_keys follow the options
@pytest.mark.parametrize(
    "ablation, count",
    [("ae", 0), ("dyn", 1), ("ode", 2), ("full", 3)],
)
def test_tsidm_out_keys_follow_the_ablation(ablation, count):
    expected = (["loss_state_rec", "loss_action_rec", *["loss_dyn", "loss_ode", "loss_tsym"][:count],
                 "ell_rec", *["ell_dyn", "ell_ode", "ell_tsym"][:count], "ell_total", "ell_sum",
                 "latent_rms", "latent_step_rms"])
    loss = TSIDMLoss(small_tsidm(), ablation=ablation)
    assert loss.out_keys == loss.out_keys_source == expected
    assert set(loss(batch()).keys()) == set(expected)


def test_tsidm_out_keys_are_read_from_the_options_not_frozen_at_first_use():
    loss = TSIDMLoss(small_tsidm())
    assert loss.out_keys == TSIDM_FULL
    loss.ablation = "dyn"
    assert "loss_tsym" not in loss.out_keys and "loss_dyn" in loss.out_keys
    assert set(loss(batch()).keys()) == set(loss.out_keys)


@pytest.mark.parametrize(
    "mode, options, expected",
    [
        ("deterministic", {}, GUIDE_DETERMINISTIC),
        ("deterministic", {"tsym_regularizer": False},
         ["loss_guide_value", "loss_guide_state", "lambda_alpha", "guide_value", "guide_step_rms"]),
        ("deterministic", {"reach_weight": 0.5},
         ["loss_guide_value", "loss_guide_state", "loss_reach", "loss_tsym",
          "lambda_alpha", "guide_value", "guide_step_rms", "tsym_to_state_ratio"]),
        ("stochastic", {}, GUIDE_STOCHASTIC),
        ("stochastic", {"tsym_regularizer": False},
         ["loss_guide_awr", "advantage", "clipped_weight_fraction", "effective_sample_fraction"]),
    ],
)
def test_guide_out_keys_follow_the_mode_and_terms(mode, options, expected):
    tsidm = small_policy_tsidm()
    loss, _, _ = make_guide_loss(mode, tsidm, **options)
    assert loss.out_keys == loss.out_keys_source == expected
    assert set(loss(latent_batch(tsidm)).keys()) == set(expected)
