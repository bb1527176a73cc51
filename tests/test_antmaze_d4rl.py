"""D4RL's AntMaze medium and large: the environment against the data and the policy that made it.

The replay and policy tests need Gymnasium-Robotics; the replay test also needs ``../shared``'s sets
(it skips with the reason where either is absent).
"""
from __future__ import annotations

import glob
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from torchrl_tels.collection.antmaze import (ACTION_NOISE, ANTMAZE_SETS, GoalReachingAnt, cell_of, collect_antmaze,
                                             next_waypoint)
from torchrl_tels.data import COLLECTED_DATASETS, load_dataset
from torchrl_tels.envs import get_task
from torchrl_tels.envs import antmaze
from torchrl_tels.errors import DatasetError

REPO = Path(__file__).resolve().parents[1]
SHARED_ANTMAZE = REPO.parent / "shared" / "datasets" / "antmaze"
try:
    antmaze.import_gymnasium_robotics()
    HAS_ROBOTICS = True
except ImportError:
    HAS_ROBOTICS = False
needs_robotics = pytest.mark.skipif(not HAS_ROBOTICS, reason='gymnasium-robotics is not installed '
                                                             '(pip install "torchrl-tels[robotics]")')
needs_shared = pytest.mark.skipif(not SHARED_ANTMAZE.is_dir(), reason=f"{SHARED_ANTMAZE} absent (../shared)")
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

SETS = ("medium-play", "medium-diverse", "large-play", "large-diverse")


@pytest.mark.parametrize("name, maze, goal_x, goal_y, steps", [
    ("antmaze-umaze-v0-10k", "umaze", (0, 1.5), (8, 9.5), 700),
    ("antmaze-medium-play-v2-100k", "medium", (20, 21.5), (20, 21.5), 1000),
    ("antmaze-medium-diverse-v2", "medium", (20, 21.5), (20, 21.5), 1000),
    ("antmaze-large-play-v2-100k", "large", (32, 33.5), (24, 25.5), 1000),
    ("antmaze-large-diverse-v2-100k", "large", (32, 33.5), (24, 25.5), 1000),
])
def test_each_name_resolves_to_its_maze_goal_range_and_episode_length(name, maze, goal_x, goal_y, steps):
    task = get_task(name)
    assert task.env_id == antmaze.ENV_IDS[maze]
    assert gym.registry[task.env_id].max_episode_steps == task.max_episode_steps == steps
    assert (task.ref_min_score, task.ref_max_score) == (0.0, 1.0)
    spec = antmaze.maze_of_task(name)
    assert spec.name == maze
    # the goal cell's centre is the low corner of the README's goal range, the range 1.5 wide
    low = spec.cell_centre(spec.goal_cell)
    assert (low[0], low[0] + 1.5) == goal_x and (low[1], low[1] + 1.5) == goal_y
    if HAS_ROBOTICS:
        env = gym.make(task.env_id)
        goals = np.array([env.reset(seed=seed)[1]["goal"] for seed in range(20)])
        env.close()
        assert goals[:, 0].min() >= goal_x[0] and goals[:, 0].max() <= goal_x[1]
        assert goals[:, 1].min() >= goal_y[0] and goals[:, 1].max() <= goal_y[1]
        assert len({tuple(g) for g in goals}) == 20  # a new goal at every reset (v2)


@needs_robotics
@pytest.mark.parametrize("maze", ["medium", "large"])
def test_walls_stand_where_d4rl_maps_put_them(maze):
    """Every wall block of the simulated maze sits on a wall cell of D4RL's map, in D4RL's frame."""
    import mujoco

    env = antmaze.AntMazeD4RLEnv(maze)
    env.reset(seed=0)  # positions are computed on the first forward pass
    spec = env.maze
    blocks = [env.data.geom_xpos[g][:2] + spec.xy_offset for g in range(env.model.ngeom)
              if (mujoco.mj_id2name(env.model, mujoco.mjtObj.mjOBJ_GEOM, g) or "").startswith("block")]
    env.close()
    cells = {(int(round(y / 4 + 1)), int(round(x / 4 + 1))) for x, y in blocks}
    walls = {(i, j) for i, row in enumerate(spec.rows) for j, c in enumerate(row) if c == "1"}
    assert len(blocks) == len(walls) and cells == walls


@needs_robotics
def test_maze_envs_leave_no_model_files(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TORCHRL_TELS_CACHE", str(tmp_path / "cache"))
    from torchrl_tels.envs.pointmaze import make_pointmaze_env

    for env_id in antmaze.ENV_IDS.values():
        gym.make(env_id).close()
    make_pointmaze_env("UMaze").close()
    gym.make(get_task("D4RL/antmaze/umaze-v1").env_id).close()
    assert glob.glob(str(tmp_path / "ant_maze*.xml")) == []
    assert tempfile.tempdir == str(tmp_path)  # the context put it back


@needs_robotics
@needs_shared
@pytest.mark.parametrize("name", SETS)
def test_one_step_replay_lands_on_the_stored_next_state(name):
    with np.load(SHARED_ANTMAZE / f"antmaze-{name}-v2-100k.npz") as archive:
        observations, actions, next_observations = (archive[k] for k in ("observations", "actions",
                                                                         "next_observations"))
    rows = np.random.default_rng(0).choice(len(observations), 300, replace=False)
    env = antmaze.AntMazeD4RLEnv(antmaze.maze_of_task(f"antmaze-{name}-v2").name)
    env.reset(seed=0)
    predicted = []
    for row in rows:
        env.set_state_from_observation(observations[row])
        predicted.append(env.step(actions[row])[0])
    env.close()
    error = np.abs(np.array(predicted) - next_observations[rows])
    assert float(np.median(error)) <= 1e-3
    assert float(np.median(error[:, :2])) <= 1e-3  # positions too, in D4RL's frame
    # not a vacuous match: the state moved
    assert float(np.median(np.abs(next_observations[rows] - observations[rows]))) > 1e-2


@needs_robotics
def test_d4rl_policy_reaches_its_goals_in_this_environment():
    """D4RL's policy with its waypoint controller and noise reaches play goals in the medium maze about as
    often as the data README reports (76 % of 25): a wrong observation order (or frame) leaves it at zero.
    The goal-reaching rate hardly depends on the motors' scale (10 to 60 all reach most goals), so the
    replay test above is the one that pins the action scale."""
    maze = antmaze.MAZES["medium"]
    policy, rng = GoalReachingAnt(), np.random.default_rng(0)
    goals, starts = maze.cells("g"), [c for c in maze.cells() if c not in maze.cells("g")]
    env = gym.make(antmaze.ENV_IDS["medium"])
    reached = []
    for episode in range(12):
        start = maze.cell_centre(starts[rng.integers(len(starts))]) + rng.uniform(0, 1, 2)
        goal = maze.cell_centre(goals[rng.integers(len(goals))]) + rng.uniform(0, 1.5, 2)
        observation, _ = env.reset(seed=episode, options={"start": start, "goal": goal})
        done = success = False
        while not done:
            waypoint = next_waypoint(maze, observation[:2], goal, rng)
            action = np.clip(policy(observation, waypoint - observation[:2], rng)
                             + ACTION_NOISE * rng.standard_normal(8), -1, 1)
            observation, _, success, truncated, _ = env.step(action)
            done = success or truncated
        reached.append(success)
    env.close()
    assert np.mean(reached) >= 0.5, reached


def test_waypoints_follow_the_corridors():
    """In the medium maze, from cell (2, 2) the way to the goal cell (6, 6) goes south to (3, 2) (the wall at
    (2, 3) blocks the way east); in the goal's own cell the waypoint is the goal."""
    maze, rng = antmaze.MAZES["medium"], np.random.default_rng(0)
    goal = maze.cell_centre((6, 6)) + 0.3
    assert cell_of(maze.cell_centre((2, 2)) + 0.5) == (2, 2)
    waypoint = next_waypoint(maze, maze.cell_centre((2, 2)) + 0.5, goal, rng)
    assert cell_of(waypoint) == (3, 2)
    offset = waypoint - maze.cell_centre((3, 2))
    assert np.all(offset >= 0) and np.all(offset <= 1)
    np.testing.assert_array_equal(next_waypoint(maze, goal - 0.1, goal, rng), goal)


@needs_robotics
def test_collector_makes_d4rl_arrays_and_is_seeded():
    a = collect_antmaze("medium-play", episodes=1, seed=3, progress=False)
    b = collect_antmaze("medium-play", episodes=1, seed=3, progress=False)
    np.testing.assert_array_equal(a["observations"], b["observations"])
    assert a["observations"].shape == (1001, 29) and a["actions"].shape == (1001, 8)
    np.testing.assert_array_equal(a["next_observations"][:-1], a["observations"][1:])
    assert a["timeouts"].sum() == 1 and a["timeouts"][-1]
    assert np.abs(a["actions"]).max() <= 1.0
    # rewards relabelled against the evaluation goal, drawn from the eval map's goal range
    assert 20 <= a["eval_goal"][0] <= 21.5 and 20 <= a["eval_goal"][1] <= 21.5
    near = np.linalg.norm(a["next_observations"][:, :2] - a["eval_goal"], axis=1) <= 0.5
    np.testing.assert_array_equal(a["rewards"], near.astype(np.float32))
    np.testing.assert_array_equal(a["terminals"], near)
    # play goals: the commanded goal lies in one of the map's hand-picked cells
    goal_x, goal_y = a["infos/goal"][0] - 0.75  # the cell's centre, within 0.75
    assert (round(goal_y / 4) + 1, round(goal_x / 4) + 1) in antmaze.MAZES["medium"].cells("g")


def test_collected_name_without_the_file_names_the_command(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_TELS_SHARED_DATASETS", str(tmp_path / "no-shared"))
    monkeypatch.setenv("TORCHRL_TELS_DATA", str(tmp_path / "data"))
    with pytest.raises(DatasetError, match=r"python recipes/collect_antmaze.py medium-diverse$"):
        load_dataset("antmaze-medium-diverse-v2-100k")
    assert set(COLLECTED_DATASETS) == {f"antmaze-{s}-v2-100k" for s in ANTMAZE_SETS}


@needs_robotics
def test_the_collect_command_makes_a_set_the_name_then_loads(tmp_path):
    env = {"TORCHRL_TELS_SHARED_DATASETS": str(tmp_path / "no-shared"), "TORCHRL_TELS_DATA": str(tmp_path),
           "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "recipes/collect_antmaze.py", "large-diverse", "--episodes", "1"],
                   cwd=REPO, env=env, check=True, capture_output=True)
    assert [p.name for p in tmp_path.iterdir()] == ["antmaze-large-diverse-v2-100k.npz"]  # no temp file left
    code = ("from torchrl_tels.data import load_dataset; "
            "d = load_dataset('antmaze-large-diverse-v2-100k'); print(d.shape[0], int(d['next', 'truncated'].sum()))")
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True).stdout
    assert out.split() == ["1001", "1"]


@needs_shared
def test_study_files_are_the_manifest_s():
    import hashlib

    manifest = json.loads((SHARED_ANTMAZE / "manifest.json").read_text())
    for name in SETS:
        file = f"antmaze-{name}-v2-100k.npz"
        assert hashlib.sha256((SHARED_ANTMAZE / file).read_bytes()).hexdigest() == manifest[file]["sha256"]
        data = load_dataset(f"antmaze-{name}-v2-100k")
        assert data.shape[0] == manifest[file]["transitions"]
