"""Costs that stay bounded as data grows: the monitor's fit, the after-training readings, and the plan a run prints."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from benchmarks.harness import recipe_config
from torchrl_tels.config import validate_config
from torchrl_tels.envs.monitor import DeploymentMonitor
from torchrl_tels.errors import ConfigError
from torchrl_tels.trainer import diagnostic_indices, make_monitor, print_plan
from tests.recipe_process import REPO_ROOT
from tests.test_monitor import linear_plant


def test_monitor_fits_on_whole_trajectories_up_to_its_cap(tmp_path, monkeypatch):
    data = linear_plant(6)  # 6 trajectories of 50 transitions
    seen = []
    real = DeploymentMonitor.cross_fit
    monkeypatch.setattr(DeploymentMonitor, "cross_fit",
                        classmethod(lambda cls, fit_data, **k: seen.append(fit_data) or real(fit_data, **k)))
    make_monitor(recipe_config(["budget=smoke", "monitor.max_transitions=120"]), data, tmp_path / "a")
    fitted = seen[-1]
    assert 120 <= len(fitted) < 170  # whole trajectories until the cap is reached
    _, counts = fitted["episode"].unique(return_counts=True)
    assert (counts == 50).all()
    make_monitor(recipe_config(["budget=smoke"]), data, tmp_path / "b")  # 100k: all 300 transitions
    assert len(seen[-1]) == len(data)


def test_diagnostics_read_a_seeded_subset_of_large_data():
    cfg = recipe_config(["diagnostics.max_transitions=1000"])
    assert diagnostic_indices(cfg, 1000) is None
    picked = diagnostic_indices(cfg, 50_000)
    assert len(picked) == 1000 and len(picked.unique()) == 1000 and picked.max() < 50_000
    assert torch.equal(picked, diagnostic_indices(cfg, 50_000))  # seeded by the run's seed
    assert not torch.equal(picked, diagnostic_indices(recipe_config(["diagnostics.max_transitions=1000", "seed=1"]),
                                                      50_000))


@pytest.mark.parametrize("override", ["monitor.max_transitions=10", "diagnostics.max_transitions=true"])
def test_bad_caps_are_refused(override):
    with pytest.raises(ConfigError, match="max_transitions must be null or an integer >= 100"):
        validate_config(recipe_config([override]))


def test_plan_is_printed_and_a_large_epoch_budget_warned(capsys):
    print_plan(recipe_config(["budget=paper"]), 1_000_000)
    out, err = capsys.readouterr()
    assert "plan: stage 1 3907000 TS-IDM steps (1000 epochs of 1000000 transitions), stage 2 100000 policy steps" in out
    assert "warning: tsidm.epochs=1000 on 1000000 transitions is 3907000 TS-IDM steps" in err
    print_plan(recipe_config(["budget=paper"]), 9013)  # a 10k set: 36k steps, no warning
    out, err = capsys.readouterr()
    assert "stage 1 36000 TS-IDM steps" in out and not err
    print_plan(recipe_config(["domain=adroit", "tsidm.steps=100"]), 9013)  # three β candidates
    assert "stage 1 300 TS-IDM steps (from tsidm.steps, 3 beta candidates)" in capsys.readouterr().out
    print_plan(recipe_config(["domain=adroit", "tsidm.checkpoint=/a/tsidm.pt"]), 9013)  # no stage 1 to train
    assert "stage 1 0 TS-IDM steps (the TS-IDM of tsidm.checkpoint)" in capsys.readouterr().out


def test_monitor_fitted_in_the_background_is_the_inline_one(tmp_path):
    from torchrl_tels.trainer import MonitorFit, monitor_in_background

    cfg = recipe_config(["budget=smoke", "monitor.window=4"])
    data = linear_plant(6)
    inline = MonitorFit(cfg, data, tmp_path / "inline", background=False).get()
    (tmp_path / "background").mkdir()
    background = MonitorFit(cfg, data, tmp_path / "background", background=True).get()
    assert float(background.threshold) == float(inline.threshold)
    assert float(background.window_threshold) == float(inline.window_threshold)
    for key, value in inline.state_dict().items():
        torch.testing.assert_close(background.state_dict()[key], value, rtol=0, atol=0)
    assert monitor_in_background(recipe_config(["monitor.background=true"]))
    assert not monitor_in_background(recipe_config(["monitor.background=false"]))
    with pytest.raises(ConfigError, match="monitor.background must be auto, true or false"):
        validate_config(recipe_config(["monitor.background=sometimes"]))


def test_a_failed_background_fit_is_one_monitor_error(tmp_path):
    from torchrl_tels.errors import MonitorError
    from torchrl_tels.trainer import MonitorFit

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    fit = MonitorFit(recipe_config(["budget=smoke"]), linear_plant(4), blocker / "run", background=True)
    with pytest.raises(MonitorError, match="the deployment monitor's fit failed: .*Error"):
        fit.get()
    assert fit.failed()


CHILD_OF_A_KILLED_RUN = '''
import sys, time
from pathlib import Path
from benchmarks.harness import recipe_config
from tests.test_monitor import linear_plant
from torchrl_tels.trainer import MonitorFit
fit = MonitorFit(recipe_config(["budget=smoke", "monitor.steps=1000000"]), linear_plant(6), Path(sys.argv[1]), background=True)
print(fit._process.pid, flush=True)
time.sleep(600)
'''


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_background_fit_ends_with_a_killed_run(tmp_path):
    """SIGKILL skips a run's exit handlers, which are what stop a daemon child: the fit must end all the same."""
    def cpu_seconds(pid: int) -> float:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime

    def alive(pid: int) -> bool:
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    run = subprocess.Popen([sys.executable, "-c", CHILD_OF_A_KILLED_RUN, str(tmp_path / "run")], cwd=REPO_ROOT,
                           env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.PIPE, text=True)
    child = None
    try:
        child = int(run.stdout.readline())
        deadline = time.monotonic() + 120
        while cpu_seconds(child) < 8:  # past its imports and into the ensemble's million steps
            assert time.monotonic() < deadline, "the background fit never got going"
            time.sleep(0.2)
        run.kill()
        run.wait()
        deadline = time.monotonic() + 10
        while alive(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(child), "the monitor's fit outlived the run that started it"
    finally:
        run.kill()
        if child is not None and alive(child):
            os.kill(child, signal.SIGKILL)
