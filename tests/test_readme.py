"""README.md, the front page: its example runs, its commands are the ones CI and users run, its links resolve.

The Python block under ``<!-- test:example -->`` is executed as written (a few steps of each stage), then its
actor is checked against the env it was built for; the Quick-start commands are checked verbatim, because
``.ci/run`` reads the line after ``<!-- ci:test -->``.
"""
from __future__ import annotations

import re
import time
from pathlib import Path

import torch

from torchrl_tels.data import make_offline_replay_buffer

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"


def _block_after(marker: str, language: str) -> str:
    text = README.read_text()
    assert marker in text, f"README.md lost its {marker} marker"
    match = re.match(rf"\s*```{language}\n(.*?)\n```", text.split(marker, 1)[1], re.DOTALL)
    assert match, f"no ```{language} block right after {marker}"
    return match.group(1)


def test_readme_example_runs_and_its_actor_acts_within_the_envs_bounds(monkeypatch):
    monkeypatch.chdir(REPO)
    torch.set_num_threads(1)
    namespace: dict = {"__name__": "readme_example"}
    start = time.perf_counter()
    exec(compile(_block_after("<!-- test:example -->", "python"), "README.md example", "exec"), namespace)
    assert time.perf_counter() - start < 30, "the README example should stay a seconds-long run"
    env, actor, tsidm = namespace["env"], namespace["actor"], namespace["tsidm"]
    assert not tsidm.training and not any(p.requires_grad for p in tsidm.parameters()), "stage 2 needs a frozen TS-IDM"
    with torch.no_grad():
        action = actor(env.reset())["action"]
    assert env.action_spec.is_in(action), action
    # its trained modules give finite losses on fresh batches: raw transitions for Eq. (7), encoded ones for stage 2
    raw, encoded = make_offline_replay_buffer(namespace["data"], 64).sample(), namespace["rb"].sample()
    for name, batch in (("tsidm_loss", raw), ("value_loss", encoded), ("guide_loss", encoded)):
        losses = namespace[name](batch)
        assert all(torch.isfinite(v).all() for k, v in losses.items() if k.startswith("loss_")), name

def test_readme_keeps_the_quick_start_commands_and_the_ci_line():
    text = README.read_text()
    assert "```bash\nbash scripts/bootstrap.sh && .venv/bin/python recipes/tels_offline.py\n```" in text
    assert _block_after("<!-- ci:test -->", "bash") == "bash scripts/bootstrap.sh && .venv/bin/python -m pytest -q -n auto --dist loadfile"


def test_readme_fits_on_a_front_page_and_links_the_report():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    head = text.split("## Quick start", 1)[0]
    assert "(study/REPORT.md)" in head, "the top of README links the reproduction report"


def _anchor(heading: str) -> str:
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_links_resolve():
    for target in re.findall(r"\]\(([^)\s]+)\)", README.read_text()):
        if target.startswith(("http://", "https://")):
            continue
        path, _, anchor = target.partition("#")
        resolved = REPO / path if path else README
        assert resolved.exists(), f"README.md links to a missing {target}"
        if anchor:
            headings = re.findall(r"^#+ (.+)$", resolved.read_text(), re.MULTILINE)
            assert anchor in {_anchor(h) for h in headings}, f"README.md links to a missing heading {target}"
