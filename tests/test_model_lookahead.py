"""``study.model_lookahead``: the latent rollout against the TS-IDM's maps stepped by hand, and
the one-step lookahead against ``model_selection``'s own reading of V at the predicted next latent."""
from __future__ import annotations

import pytest
import torch

from study import model_lookahead, model_selection
from study.proposal_cap import load_finished_run
from torchrl_tels.diagnostics import latent_statistics
from torchrl_tels.modules import make_tels_actor


@pytest.fixture(scope="module")
def finished_run(finished_recipe_run):
    torch.set_num_threads(1)
    return load_finished_run(finished_recipe_run, episodes=2)


def test_the_lookahead_rolls_the_actor_through_the_forward_model(finished_run):
    run = finished_run
    actor = make_tels_actor(run.tsidm, run.actor[1], run.env.action_spec_unbatched)
    guide, head = run.actor[1].module, actor[-1].module
    chooser = model_selection.LatentActionChoice(run.tsidm, guide, head, torch.full((run.tsidm.latent_action_dim,), 0.3),
                                                 model_selection.own_action)
    _, _, predicted = chooser.candidates(run.data["observation"][:9])
    ahead = model_lookahead.lookahead_latents(chooser, predicted, lookaheads=(1, 3))
    assert sorted(ahead) == [1, 3]
    torch.testing.assert_close(ahead[1], predicted)
    with torch.no_grad():
        z = predicted
        for _ in range(2):  # Eq. (11)'s latent action for the guide's proposal, then Eq. (6)'s forward model
            z = z + run.tsidm.forward_dynamics(z, run.tsidm.infer_latent_action(z, guide(z)))
    torch.testing.assert_close(ahead[3], z)
    assert not torch.allclose(ahead[3], ahead[1])  # the model moves: the test can tell L = 1 from L = 3


def test_a_reading_at_lookahead_one_is_model_selections_local_model_rank(finished_recipe_run, monkeypatch):
    monkeypatch.setattr(model_selection, "start_rows", lambda data: torch.arange(12))
    monkeypatch.setattr(model_selection, "LOCAL_STATES", 12)
    monkeypatch.setattr(model_selection, "EPISODES", 1)
    monkeypatch.setattr(model_lookahead, "LOOKAHEADS", (1, 4))
    record = model_lookahead.model_lookahead(finished_recipe_run, horizon=5)
    reference = model_selection.model_selection(finished_recipe_run, horizon=5)
    assert record["states"] == 12 and record["horizon"] == 5 and sorted(record["lookahead"]) == ["1", "4"]
    assert record["actor_return"] == pytest.approx(reference["local"]["actor_return"])
    assert record["lookahead"]["1"]["rank"] == pytest.approx(reference["local"]["model_rank"])
    assert all(-1.0 <= reading["rank"] <= 1.0 and reading["drift"] > 0 for reading in record["lookahead"].values())
    # the spread against the diagnostics' per-dimension latent RMS: √(dims) × it, over the RMS latent step
    run = load_finished_run(finished_recipe_run, episodes=1)
    with torch.no_grad():
        stats = latent_statistics(run.tsidm, run.data["observation"], run.data["next", "observation"])
    expected = stats["latent_rms"] * run.tsidm.latent_state_dim ** 0.5 / stats["latent_step_rms"]
    assert record["spread"] == pytest.approx(expected, rel=1e-3)  # their variances differ by n / (n - 1)
    header, rule, row = model_lookahead.table({("arm", "task", 0): record}).splitlines()
    cells = dict(zip(header.strip("| ").split(" | "), row.strip("| ").split(" | ")))
    assert len(cells) == rule.count("---")
    assert cells["rank at L = 1 (drift)"] == f"{record['lookahead']['1']['rank']:.2f} ({record['lookahead']['1']['drift']:.3g})"
    assert cells["data's latent spread"] == f"{record['spread']:.1f}"
