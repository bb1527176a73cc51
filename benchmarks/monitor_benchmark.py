"""Does the deployment monitor tell off-data transitions and stretches from in-distribution ones, and
does its calibration hold on new data? (AUROC, false alarms, detection delay)

For one setting and seed (``run``), the data's trajectories are split three ways: a test fifth, never
used for fitting or calibration, and the rest, from which the monitors are made:

* ``split``: a TS-IDM (the recipe's stage 1, ``--tsidm-steps``), the one-step dynamics ensemble and
  the nearest-state bank fitted to three quarters of the rest, calibrated on the last quarter
  (:meth:`DeploymentMonitor.fit <torchrl_tels.envs.DeploymentMonitor.fit>`). Every detector's AUROC
  comes from this monitor, so each term's score is compared on the same fit;
* ``cross_fit``: the ensemble and the bank, calibrated on out-of-fold scores of all of the rest
  (:meth:`DeploymentMonitor.cross_fit <torchrl_tels.envs.DeploymentMonitor.cross_fit>`, 5 folds);
* ``in_sample``: the split monitor's detectors calibrated on their own training data: the
  calibration the monitor had before, kept as the control.

Shifted data, by setting:

* ``hopper`` (hopper-medium-v2-10k, Hopper-v4):
  (a) ``random_actions``: uniform actions replayed from test states, and random-action episodes
  from the env's reset (for windows); ``other_dataset``: hopper-medium-replay-v2-10k;
  (b) ``mass_x0.7`` … ``friction_x1.3``: the TELS policy's own episodes in a changed plant (every
  body mass, or every geom's sliding friction, scaled) against its episodes in the nominal plant,
  and the data's actions replayed from test states in the changed plant (against the same replay in
  the nominal plant); detection delay: episodes whose plant changes at step ``--change-at``.
  The policy is a default recipe run (``--policy-runs``; trained there when absent);
* ``walker`` (walker2d-medium-v2-10k, Walker2d-v4): (a) random actions and (b) replays only, the
  setting the default score was not chosen on;
* ``maze`` (pointmaze-medium with the OOD deletion test's five regions removed): (c)
  ``deleted_regions``: transitions from inside the regions, and their runs of consecutive steps
  (for windows).

Per-transition AUROC (Mann-Whitney, 0.5 = chance) for every term and candidate combination;
window-level AUROC of the running mean of each standardized score over ``k`` steps of an episode
(windows that lie wholly inside one episode, ``--windows``); the test set's flag rate at the
0.99 threshold and its window alarms per 1,000 steps at the 0.999 window threshold, for every
calibration. Run from the repository root::

    python -m benchmarks.monitor_benchmark run --setting hopper --seed 0 --policy-runs runs/monitor_policies
    python -m benchmarks.monitor_benchmark table            # benchmarks/results/monitor/MONITOR.md
    python -m benchmarks.monitor_benchmark run --setting hopper --tsidm-steps 20 --ensemble-steps 20 --folds 2 \\
        --episodes 1 --out /tmp/m --policy-runs /tmp/p  # smoke (trains a smoke policy)

Writes ``benchmarks/results/monitor/<setting>_seed<k>.json`` (skipped when it exists unless ``--force``).
"""
from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from benchmarks.harness import command_line, invocation, machine_description, REPO, repo_relative, run_recipe, \
    portable, recipe_config, skip_existing, write_generated, write_result
from torchrl_tels.data import delete_regions, load_dataset, points_in_boxes, split_trajectories, trajectory_ids
from torchrl_tels.envs import DeploymentMonitor
from torchrl_tels.envs.monitor import DEFAULT_COMBINATION, running_mean, SCORE_TERMS, steps_into_trajectory
from torchrl_tels.trainer import fit_tsidm, RunState
from torchrl_tels.run_folder import RunFolder

RESULTS = REPO / "benchmarks" / "results" / "monitor"
TABLE = RESULTS / "MONITOR.md"
SETTINGS = {
    "hopper": {"dataset": "hopper-medium-v2-10k", "env": "Hopper-v4", "other": "hopper-medium-replay-v2-10k",
               "policy": True, "domain": "mujoco"},
    "walker": {"dataset": "walker2d-medium-v2-10k", "env": "Walker2d-v4", "other": None, "policy": False,
               "domain": "mujoco"},
    "maze": {"dataset": None, "env": None, "other": None, "policy": False, "domain": "maze"},
}
PLANTS = {"mass_x0.7": ("mass", 0.7), "mass_x1.3": ("mass", 1.3),
          "friction_x0.7": ("friction", 0.7), "friction_x1.3": ("friction", 1.3)}
#: Candidate ``ood_score`` combinations, each the mean of its terms' standardized log scores.
CANDIDATES = {
    "combined (default)": DEFAULT_COMBINATION,
    "combined, ensemble terms + nearest": ("model_residual", "model_disagreement", "nearest_state"),
    "combined, all terms": SCORE_TERMS,
}
CALIBRATIONS = ("in_sample", "split", "cross_fit")
MIN_WINDOWS = 20  # fewer full windows on a side: no window AUROC
#: The order of the shifted sets in the table: (a) other behaviour, (c) the maze's regions, (b) changed plants.
SET_ORDER = ("random_actions (replay)", "random_actions (episodes)", "other_dataset", "deleted_regions",
             "nominal replay (control)", *(f"{plant} (replay)" for plant in PLANTS),
             "policy, nominal plant (vs test data)", *(f"policy, {plant}" for plant in PLANTS))


# ---------------------------------------------------------------------- AUROC
def auroc(negatives, positives) -> float:
    """P(positive score > negative score) + P(tie) / 2: the Mann-Whitney U divided by n_pos * n_neg.

    Ranks with ties averaged; a detector that scores the positives (shifted) higher is above 0.5.
    """
    negatives, positives = np.asarray(negatives, float).ravel(), np.asarray(positives, float).ravel()
    if not len(negatives) or not len(positives):
        raise ValueError("auroc needs at least one negative and one positive score.")
    scores = np.concatenate([negatives, positives])
    if not np.isfinite(scores).all():
        raise ValueError("auroc: the scores hold NaN or inf.")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ends = np.cumsum(counts)
    ranks = ((ends - counts + 1 + ends) / 2)[inverse]  # average rank of each distinct value, 1-based
    n_pos, n_neg = len(positives), len(negatives)
    u = ranks[n_neg:].sum() - n_pos * (n_pos + 1) / 2
    return float(u / (n_pos * n_neg))


def full_windows(score: torch.Tensor, trajectory: torch.Tensor, k: int) -> torch.Tensor:
    """The running mean over ``k`` steps at every step whose window lies wholly inside its trajectory."""
    return running_mean(score, k, trajectory)[steps_into_trajectory(trajectory) >= k - 1]


# ----------------------------------------------------------------------- data
def as_transitions(observation, action, next_observation, episode=None) -> TensorDict:
    as_tensor = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)
    observation = as_tensor(observation)
    td = TensorDict({"observation": observation, "action": as_tensor(action),
                     ("next", "observation"): as_tensor(next_observation)}, batch_size=[len(observation)])
    if episode is not None:
        td["episode"] = torch.as_tensor(np.asarray(episode), dtype=torch.long)
    return td


def make_env(env_id: str, plant: tuple[str, float] | None = None):
    import gymnasium as gym

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the v4 MuJoCo envs are "out of date"
        env = gym.make(env_id)
    if plant is not None:
        change_plant(env, plant)
    return env


def change_plant(env, plant: tuple[str, float]) -> None:
    """Scales every body's mass, or every geom's sliding friction, in place (the next step feels it)."""
    what, factor = plant
    model = env.unwrapped.model
    if what == "mass":
        model.body_mass[:] *= factor
    else:
        model.geom_friction[:, 0] *= factor


def replay(env_id: str, states: TensorDictBase, actions: np.ndarray, plant=None) -> TensorDict:
    """One env step from each data state (set through ``set_state``) with ``actions``. The observation
    holds qpos without the x position (which the dynamics do not depend on) and qvel."""
    env = make_env(env_id, plant)
    inner = env.unwrapped
    env.reset(seed=0)
    nq = inner.model.nq
    observation = states["observation"].double().numpy()
    next_observation = np.empty_like(observation)
    for i, (obs, act) in enumerate(zip(observation, actions)):
        inner.set_state(np.concatenate([[0.0], obs[: nq - 1]]), obs[nq - 1:])
        next_observation[i] = inner.step(np.asarray(act, dtype=np.float64))[0]
    env.close()
    return as_transitions(observation, actions, next_observation)


def episodes(env_id: str, act, count: int, seed: int, *, plant=None, change_at: int | None = None,
             max_steps: int = 1000) -> TensorDict:
    """``count`` episodes of ``act(observation) -> action``, concatenated with an ``"episode"`` entry.
    With ``change_at``, the plant changes after that many steps of each episode; else from the start."""
    rows = {"observation": [], "action": [], "next": [], "episode": []}
    for e in range(count):
        env = make_env(env_id, plant if change_at is None else None)
        observation, _ = env.reset(seed=seed * 1000 + e)
        for t in range(max_steps):
            if change_at is not None and t == change_at:
                change_plant(env, plant)
            action = act(observation)
            next_observation, _, terminated, truncated, _ = env.step(action)
            for key, value in zip(rows, (observation, action, next_observation, e)):
                rows[key].append(value)
            observation = next_observation
            if terminated or truncated:
                break
        env.close()
    return as_transitions(rows["observation"], rows["action"], rows["next"], rows["episode"])


def policy_actor(run_dir: Path, env_id: str):
    from torchrl_tels.envs import make_eval_env
    from torchrl_tels.export import PolicyProgram
    from torchrl_tels.modules import load_tels_actor, TSIDM

    spec = make_eval_env(env_id).action_spec
    folder = RunFolder(run_dir)
    program = PolicyProgram(load_tels_actor(folder.policy_path, TSIDM.load(folder.tsidm_path), spec))

    def act(observation):
        with torch.no_grad():
            return program(torch.as_tensor(observation, dtype=torch.float32)[None])[0].double().numpy()
    return act


def ensure_policy(runs: Path, seed: int, threads: int) -> tuple[Path, str]:
    """The default recipe run of ``seed`` under ``runs`` (trained when absent) and its command."""
    run_dir = runs / f"hopper-medium_seed{seed}"
    overrides = [f"seed={seed}", f"threads={threads}", f"run_dir={run_dir}", "precision=auto"]
    command = command_line(["python", "recipes/tels_offline.py", *overrides])
    if not RunFolder(run_dir).is_finished:
        run_recipe(overrides, threads)
    return run_dir, command


# ------------------------------------------------------------------ scoring
class Scorer:
    """Standardized log scores of every term (by the split monitor's calibration) and of the candidates."""

    def __init__(self, monitor: DeploymentMonitor) -> None:
        self.monitor = monitor

    def __call__(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        m = self.monitor
        raw = m._data_scores(td)
        u = m.standardize(raw)
        out = {term: u[:, i] for i, term in enumerate(m.terms)}
        for name, terms in CANDIDATES.items():
            out[name] = u[:, [m.terms.index(t) for t in terms]].mean(-1)
        return out


def transition_aurocs(reference: dict, shifted: dict) -> dict[str, float]:
    return {name: auroc(reference[name].numpy(), shifted[name].numpy()) for name in reference}


def window_aurocs(reference: dict, reference_traj, shifted: dict, shifted_traj, windows) -> dict:
    out = {}
    for name in reference:
        out[name] = {}
        for k in windows:
            neg = full_windows(reference[name], reference_traj, k)
            pos = full_windows(shifted[name], shifted_traj, k)
            out[name][str(k)] = auroc(neg.numpy(), pos.numpy()) if min(len(neg), len(pos)) >= MIN_WINDOWS else None
    return out


def alarm_rates(monitor: DeploymentMonitor, td: TensorDictBase) -> dict[str, float]:
    """Flag rate per transition, window-alarm steps and alarm onsets per 1,000 steps, on trajectories ``td``."""
    scores = monitor.scores(td["observation"], td["action"], td["next", "observation"])["ood_score"]
    trajectory = trajectory_ids(td)
    window = running_mean(scores, monitor.window, trajectory)
    alarm = window > float(monitor.window_threshold)
    onset = alarm.clone()
    onset[1:] &= ~(alarm[:-1] & (trajectory[1:] == trajectory[:-1]))
    return {"flag_rate": float((scores > monitor.threshold).float().mean()),
            "window_alarm_steps_per_1000": 1000 * float(alarm.float().mean()),
            "window_alarm_onsets_per_1000": 1000 * float(onset.float().mean()),
            "steps": len(scores)}


def detection_delays(monitor: DeploymentMonitor, td: TensorDictBase, change_at: int) -> dict:
    """Steps from the change to the first window alarm, per episode (None: no alarm before the episode ended)."""
    scores = monitor.scores(td["observation"], td["action"], td["next", "observation"])["ood_score"]
    delays, before, lengths = [], 0, []
    for e in td["episode"].unique().tolist():
        mask = td["episode"] == e
        window = running_mean(scores[mask], monitor.window)
        alarm = (window > float(monitor.window_threshold)).nonzero().squeeze(-1)
        before += int(bool((alarm < change_at).any()))
        after = alarm[alarm >= change_at]
        delays.append(int(after[0]) - change_at if len(after) else None)
        lengths.append(int(mask.sum()))
    return {"delays": delays, "episode_lengths": lengths, "alarm_before_change": before}


# ------------------------------------------------------------------------ run
def fit_tsidm_on(train: TensorDictBase, domain: str, seed: int, steps: int):
    cfg = recipe_config([f"domain={domain}", f"seed={seed}", f"tsidm.steps={steps}", "checkpoint.interval=1000000000",
                         "precision=auto"])
    beta = 1.0 if cfg.tsidm.beta == "auto" else float(cfg.tsidm.beta)
    torch.manual_seed(seed)
    with tempfile.TemporaryDirectory() as scratch:
        tsidm, final, _ = fit_tsidm(cfg, train, beta, RunState(config={}), Path(scratch))
    return tsidm, final


def maze_data(seed: int):
    from benchmarks.ood_deletion import ensure_dataset, SETUPS

    setup, boxes = SETUPS["pointmaze-medium"]()
    ensure_dataset(setup)
    full = load_dataset(setup.dataset)
    inside = points_in_boxes(full, boxes)
    rows = inside.nonzero().squeeze(-1)
    # A run of consecutive steps inside the regions is one trajectory of the shifted set.
    breaks = torch.ones(len(rows), dtype=torch.bool)
    breaks[1:] = (rows[1:] != rows[:-1] + 1) | (full["episode"][rows[1:]] != full["episode"][rows[:-1]])
    regions = full[rows]
    regions["episode"] = breaks.cumsum(0) - 1
    return setup.dataset, delete_regions(full, boxes, 1.0, seed=seed), regions, boxes


def setting_data(setting: str, seed: int) -> tuple[str, TensorDictBase, TensorDictBase | None]:
    """The setting's dataset name, its in-distribution data, and for the maze the runs inside the deleted regions."""
    if setting == "maze":
        dataset, data, inside, _ = maze_data(seed)
        return dataset, data, inside
    return SETTINGS[setting]["dataset"], load_dataset(SETTINGS[setting]["dataset"]), None


def run(args) -> dict:
    torch.set_num_threads(args.threads)
    print(f"torch threads pinned to {args.threads}", flush=True)
    setting = SETTINGS[args.setting]
    clock = {}
    dataset, data, inside = setting_data(args.setting, args.seed)
    rest, test = split_trajectories(data, 0.8, args.seed)
    fit_part, cal_part = split_trajectories(rest, 0.75, args.seed + 1)
    print(f"{dataset}: fit {len(fit_part)}, calibration {len(cal_part)}, test {len(test)} transitions", flush=True)

    start = time.perf_counter()
    tsidm, tsidm_final = fit_tsidm_on(fit_part, setting["domain"], args.seed, args.tsidm_steps)
    clock["tsidm_s"] = time.perf_counter() - start
    options = {"steps": args.ensemble_steps, "seed": args.seed, "window": args.window, "precision": args.precision}
    start = time.perf_counter()
    monitors = {"split": DeploymentMonitor.fit(fit_part, cal_part, tsidm=tsidm, **options)}
    clock["split_s"] = time.perf_counter() - start
    start = time.perf_counter()
    monitors["cross_fit"] = DeploymentMonitor.cross_fit(rest, folds=args.folds, **options)
    clock["cross_fit_s"] = time.perf_counter() - start
    split = monitors["split"]
    in_sample = DeploymentMonitor(tsidm=split.tsidm, dynamics=split.dynamics, states=split.states,
                                  window=args.window)
    in_sample.calibrate(fit_part)
    monitors = {"in_sample": in_sample, **monitors}
    score = Scorer(split)
    test_scores, test_traj = score(test), trajectory_ids(test)

    transition, windows, shifted_sizes = {}, {}, {}

    def compare(name, reference, reference_traj, td, traj=None):
        shifted = score(td)
        shifted_sizes[name] = len(td)
        transition[name] = transition_aurocs(reference, shifted)
        if traj is not None:
            windows[name] = window_aurocs(reference, reference_traj, shifted, traj, args.windows)
        return shifted

    rng = np.random.default_rng(args.seed)
    if args.setting == "maze":
        compare("deleted_regions", test_scores, test_traj, inside, trajectory_ids(inside))
    else:
        env_id = setting["env"]
        states = test if len(test) <= args.replay else test[torch.randperm(
            len(test), generator=torch.Generator().manual_seed(args.seed))[: args.replay]]
        random = rng.uniform(-1.0, 1.0, size=tuple(states["action"].shape))
        compare("random_actions (replay)", test_scores, test_traj, replay(env_id, states, random))
        action_dim = states["action"].shape[-1]
        random_episodes = episodes(env_id, lambda _: rng.uniform(-1.0, 1.0, action_dim), args.episodes * 4,
                                   args.seed)
        compare("random_actions (episodes)", test_scores, test_traj, random_episodes,
                trajectory_ids(random_episodes))
        if setting["other"]:
            other = load_dataset(setting["other"])
            compare("other_dataset", test_scores, test_traj, other, trajectory_ids(other))
        nominal_replay = replay(env_id, states, states["action"].numpy())
        nominal_scores = compare("nominal replay (control)", test_scores, test_traj, nominal_replay)
        for name, plant in PLANTS.items():
            compare(f"{name} (replay)", nominal_scores, None, replay(env_id, states, states["action"].numpy(), plant))

    policy, delays, rollout_rates = None, {}, {}
    if setting["policy"]:
        run_dir, command = ensure_policy(args.policy_runs, args.seed, args.threads)
        import json

        record = RunFolder(run_dir).read_results()
        policy = {"command": command, "final_normalized_score_mean": record["final_normalized_score_mean"]}
        act = policy_actor(run_dir, setting["env"])
        start = time.perf_counter()
        nominal = episodes(setting["env"], act, args.episodes, args.seed)
        nominal_scores = compare("policy, nominal plant (vs test data)", test_scores, test_traj, nominal,
                                 trajectory_ids(nominal))
        rollout_rates["nominal"] = {m: alarm_rates(monitor, nominal) for m, monitor in monitors.items()}
        for name, plant in PLANTS.items():
            changed = episodes(setting["env"], act, args.episodes, args.seed, plant=plant)
            compare(f"policy, {name}", nominal_scores, trajectory_ids(nominal), changed, trajectory_ids(changed))
            rollout_rates[name] = {m: alarm_rates(monitor, changed) for m, monitor in monitors.items()}
            switched = episodes(setting["env"], act, args.episodes, args.seed + 500, plant=plant,
                                change_at=args.change_at)
            delays[name] = {m: detection_delays(monitors[m], switched, args.change_at) for m in ("split", "cross_fit")}
        clock["rollouts_s"] = time.perf_counter() - start

    calibration = {m: {"threshold": float(monitor.threshold), "window_threshold": float(monitor.window_threshold),
                       "test": alarm_rates(monitor, test)} for m, monitor in monitors.items()}
    return {
        "command": invocation(),
        "setting": args.setting,
        "dataset": dataset,
        "env": setting["env"],
        "seed": args.seed,
        "sizes": {"fit": len(fit_part), "calibration": len(cal_part), "test": len(test), **shifted_sizes},
        "trajectories": {"fit": int(trajectory_ids(fit_part)[-1]) + 1, "calibration": int(trajectory_ids(cal_part)[-1]) + 1,
                         "test": int(test_traj[-1]) + 1},
        "tsidm_steps": args.tsidm_steps,
        "tsidm_final_loss": tsidm_final,
        "ensemble": {"members": 5, "steps": args.ensemble_steps, "folds": args.folds, "precision": args.precision},
        "window": args.window,
        "nominal": {"flag_rate": 0.01, "window_alarm_steps_per_1000": 1.0},
        "calibration": calibration,
        "transition_auroc": transition,
        "window_auroc": windows,
        "policy": policy,
        "policy_alarm_rates": rollout_rates,
        "change_at": args.change_at if delays else None,
        "detection_delay": delays,
        "wall_s": clock,
        "threads": args.threads,
        "machine": machine_description(),
    }


def run_far(args) -> dict:
    """Every trajectory held out once: the false-alarm rates of each calibration on data no part of it saw."""
    torch.set_num_threads(args.threads)
    print(f"torch threads pinned to {args.threads}", flush=True)
    dataset, data, _ = setting_data(args.setting, args.seed)
    trajectory = trajectory_ids(data)
    count = int(trajectory[-1]) + 1
    order = torch.randperm(count, generator=torch.Generator().manual_seed(args.seed))
    fold_of = torch.empty(count, dtype=torch.long)
    fold_of[order] = torch.arange(count) % args.outer_folds
    options = {"steps": args.ensemble_steps, "seed": args.seed, "window": args.window, "precision": args.precision}
    folds = []
    for k in range(args.outer_folds):
        held = fold_of[trajectory] == k
        rest, test = data[~held], data[held]
        start = time.perf_counter()
        monitors = {"cross_fit": DeploymentMonitor.cross_fit(rest, folds=args.folds, **options)}
        fit_part, cal_part = split_trajectories(rest, 0.75, args.seed + 1)
        monitors["split"] = DeploymentMonitor.fit(fit_part, cal_part, **options)
        in_sample = DeploymentMonitor(dynamics=monitors["split"].dynamics, states=monitors["split"].states,
                                      window=args.window)
        in_sample.calibrate(fit_part)
        monitors["in_sample"] = in_sample
        folds.append({"test_trajectories": int(held.sum() and trajectory_ids(test)[-1] + 1),
                      "rates": {m: alarm_rates(monitor, test) for m, monitor in monitors.items()},
                      "wall_s": time.perf_counter() - start})
        print(f"outer fold {k}: " + ", ".join(f"{m} {r['flag_rate']:.3%}" for m, r in folds[-1]["rates"].items()),
              flush=True)
    pooled = {}
    for method in folds[0]["rates"]:
        steps = sum(f["rates"][method]["steps"] for f in folds)
        pooled[method] = {key: sum(f["rates"][method][key] * f["rates"][method]["steps"] for f in folds) / steps
                          for key in ("flag_rate", "window_alarm_steps_per_1000", "window_alarm_onsets_per_1000")}
    return {"command": invocation(), "setting": args.setting, "dataset": dataset, "seed": args.seed,
            "trajectories": count, "outer_folds": args.outer_folds,
            "ensemble": {"members": 5, "steps": args.ensemble_steps, "folds": args.folds, "precision": args.precision},
            "window": args.window,
            "nominal": {"flag_rate": 0.01, "window_alarm_steps_per_1000": 1.0},
            "pooled": pooled, "folds": folds, "threads": args.threads, "machine": machine_description()}


# ---------------------------------------------------------------------- table
def _load(results: Path) -> dict[str, list[dict]]:
    import json

    runs = {}
    for path in sorted(results.glob("*_seed*.json")):
        record = json.loads(path.read_text())
        kind = "far" if path.name.startswith("far_") else "run"
        runs.setdefault(record["setting"], {"run": [], "far": []})[kind].append(record)
    return runs


def _cell(values) -> str:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not values:
        return "–"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{statistics.mean(values):.3f} ({min(values):.2f}–{max(values):.2f})"


SIMPLE_DETECTORS = ("model_residual", "model_disagreement", "nearest_state")
DEFAULT = "combined (default)"


def _targets(runs: dict[str, dict[str, list[dict]]]) -> list[str]:
    """The three targets, each read off the JSONs: held-out false alarms, the default against the simple
    detectors on (a) and (c), and window AUROC on the mass changes."""
    def mean(values):
        return statistics.mean(values) if values else math.nan

    lines = ["## The targets, as measured", "",
             "| target | setting | measured (mean over seeds) | met |", "|---|---|---|---|"]
    for setting, kinds in runs.items():
        for record_set, label in ((kinds["far"], "every trajectory held out once"),
                                  (kinds["run"], "one held-out fifth per seed")):
            if not record_set:
                continue
            if record_set is kinds["far"]:
                ratio = mean([r["pooled"]["cross_fit"]["flag_rate"] / r["nominal"]["flag_rate"] for r in record_set])
            else:
                ratio = mean([r["calibration"]["cross_fit"]["test"]["flag_rate"] / r["nominal"]["flag_rate"]
                              for r in record_set])
            lines.append(f"| held-out false-alarm rate 0.5×–1.5× nominal (default: cross_fit, q = 0.99) | {setting}, "
                         f"{label} | {ratio:.2f}× | {'yes' if 0.5 <= ratio <= 1.5 else 'no'} |")
    for setting, kinds in runs.items():
        records = kinds["run"]
        for name in ("random_actions (replay)", "random_actions (episodes)", "other_dataset", "deleted_regions"):
            if not records or name not in records[0]["transition_auroc"]:
                continue
            ours = mean([r["transition_auroc"][name][DEFAULT] for r in records])
            best = max(SIMPLE_DETECTORS, key=lambda d: mean([r["transition_auroc"][name][d] for r in records]))
            theirs = mean([r["transition_auroc"][name][best] for r in records])
            lines.append(f"| per-transition AUROC of the default ≥ the best simple detector | {setting}, {name} | "
                         f"{ours:.3f} vs {theirs:.3f} ({best}) | {'yes' if ours >= theirs else 'no'} |")
    for setting, kinds in runs.items():
        records = kinds["run"]
        for plant in ("mass_x0.7", "mass_x1.3"):
            name = f"policy, {plant}"
            if not records or name not in records[0]["window_auroc"]:
                continue
            by_k = {int(k): mean([r["window_auroc"][name][DEFAULT][k] for r in records])
                    for k in records[0]["window_auroc"][name][DEFAULT]}
            reached = [k for k in sorted(by_k) if by_k[k] >= 0.9]
            lines.append(f"| window AUROC ≥ 0.9 with k ≤ 200 | {setting}, {name} | "
                         + ", ".join(f"k = {k}: {v:.3f}" for k, v in sorted(by_k.items()))
                         + f" | {'yes, from k = ' + str(reached[0]) if reached and reached[0] <= 200 else 'no'} |")
    return lines + [""]


def _precision_section(runs: dict, bf16: dict) -> list[str]:
    """The default score with the ensemble trained in bf16 against fp32, paired by setting and seed."""
    lines = ["## The ensemble trained in bf16 against fp32 (paired by seed)", "",
             "The same runs with `--precision bf16` (the ensemble's forward passes under bf16 autocast), results in "
             "`bf16/`. Cells: bf16 minus fp32 for the default score, mean over the paired seeds (min–max), n pairs.",
             "", "| setting | measure | bf16 − fp32 | n |", "|---|---|---|---|"]
    for setting, kinds in bf16.items():
        ours = {r["seed"]: r for r in runs.get(setting, {}).get("run", [])}
        pairs = [(r, ours[r["seed"]]) for r in kinds["run"] if r["seed"] in ours]
        for name in SET_ORDER:
            if pairs and name in pairs[0][0]["transition_auroc"]:
                diffs = [b["transition_auroc"][name][DEFAULT] - a["transition_auroc"][name][DEFAULT] for b, a in pairs]
                lines.append(f"| {setting} | AUROC, {name} | {statistics.mean(diffs):+.3f} ({min(diffs):+.3f}–"
                             f"{max(diffs):+.3f}) | {len(diffs)} |")
        if pairs:
            diffs = [b["calibration"]["cross_fit"]["test"]["flag_rate"] - a["calibration"]["cross_fit"]["test"][
                "flag_rate"] for b, a in pairs]
            lines.append(f"| {setting} | flag rate on the test fifth (cross_fit) | {statistics.mean(diffs):+.4f} "
                         f"({min(diffs):+.4f}–{max(diffs):+.4f}) | {len(diffs)} |")
            times = [(b["wall_s"]["cross_fit_s"], a["wall_s"]["cross_fit_s"]) for b, a in pairs]
            lines.append(f"| {setting} | cross_fit wall time, bf16 / fp32 (two 1-thread jobs at a time) | "
                         f"{statistics.mean(x / y for x, y in times):.2f}× | {len(times)} |")
        far_ours = {r["seed"]: r for r in runs.get(setting, {}).get("far", [])}
        for r in kinds["far"]:
            if r["seed"] in far_ours:
                d = r["pooled"]["cross_fit"]["flag_rate"] - far_ours[r["seed"]]["pooled"]["cross_fit"]["flag_rate"]
                lines.append(f"| {setting} | flag rate, every trajectory held out once (cross_fit) | {d:+.4f} | 1 |")
    return lines + [""]


def render(runs: dict[str, dict[str, list[dict]]], bf16: dict | None = None) -> str:
    lines = ["# Deployment monitor: detection and calibration (generated)", "",
             "Generated by `python -m benchmarks.monitor_benchmark table` from the JSONs beside this file; "
             "do not edit. Each cell: mean over seeds (min–max), n = seeds. The protocol is the docstring of "
             "`benchmarks/monitor_benchmark.py`.", ""]
    lines += _targets(runs)
    if bf16:
        lines += _precision_section(runs, bf16)
    for setting, kinds in runs.items():
        records, far = kinds["run"], kinds["far"]
        if not records:
            continue
        first = records[0]
        seeds = sorted(r["seed"] for r in records)
        machines = sorted({r["machine"].get("cpu", "?") for r in records})
        lines += [f"## {setting}: {first['dataset']} (seeds {seeds}, n = {len(records)})", "",
                  f"Commands: `{portable(first['command'])}` (and the other seeds); machine: {', '.join(machines)}, "
                  f"{first['threads']} torch thread(s). Fit/calibration/test transitions (seed {first['seed']}): "
                  f"{first['sizes']['fit']}/{first['sizes']['calibration']}/{first['sizes']['test']}, trajectories "
                  f"{first['trajectories']['fit']}/{first['trajectories']['calibration']}/"
                  f"{first['trajectories']['test']}.", ""]
        if first.get("policy"):
            scores = [r["policy"]["final_normalized_score_mean"] for r in records]
            lines += [f"Policy: `{portable(first['policy']['command'])}` per seed; final normalized score {_cell(scores)}.", ""]
        detectors = [d for d in (*SCORE_TERMS, *CANDIDATES) if d in first["transition_auroc"][
            next(iter(first["transition_auroc"]))]]
        sets = [name for name in SET_ORDER if name in first["transition_auroc"]]
        lines += ["### Per-transition AUROC", "", "| shifted set | " + " | ".join(detectors) + " |",
                  "|---|" + "---|" * len(detectors)]
        for name in sets:
            lines.append(f"| {name} | " + " | ".join(
                _cell([r["transition_auroc"][name][d] for r in records if name in r["transition_auroc"]])
                for d in detectors) + " |")
        if first["window_auroc"]:
            ks = sorted(next(iter(first["window_auroc"].values()))[detectors[0]], key=int)
            shown = ["model_residual", "nearest_state", "tsym_inconsistency", "combined (default)"]
            lines += ["", "### Window-level AUROC (running mean over k steps of an episode)", "",
                      "| shifted set | detector | " + " | ".join(f"k = {k}" for k in ks) + " |",
                      "|---|---|" + "---|" * len(ks)]
            for name in (name for name in SET_ORDER if name in first["window_auroc"]):
                for d in shown:
                    lines.append(f"| {name} | {d} | " + " | ".join(
                        _cell([r["window_auroc"][name][d][k] for r in records if name in r["window_auroc"]])
                        for k in ks) + " |")
        nominal = first["nominal"]
        lines += ["", f"### False alarms on the test trajectories (nominal: flag rate {nominal['flag_rate']:.0%}, "
                      f"window alarms {nominal['window_alarm_steps_per_1000']:g} step per 1,000; window "
                      f"{first['window']} steps)", "",
                  "| calibration | flag rate | × nominal | window-alarm steps / 1,000 | alarm onsets / 1,000 |",
                  "|---|---|---|---|---|"]
        for method in CALIBRATIONS:
            tests = [r["calibration"][method]["test"] for r in records]
            rates = [t["flag_rate"] for t in tests]
            lines.append(f"| {method} | {_cell(rates)} | {_cell([x / nominal['flag_rate'] for x in rates])} | "
                         f"{_cell([t['window_alarm_steps_per_1000'] for t in tests])} | "
                         f"{_cell([t['window_alarm_onsets_per_1000'] for t in tests])} |")
        if far:
            nominal_far = far[0]["nominal"]
            lines += ["", f"### False alarms with every trajectory held out once ({far[0]['outer_folds']} outer folds "
                          f"over {far[0]['trajectories']} trajectories; seeds {sorted(r['seed'] for r in far)})", "",
                      f"Command: `{far[0]['command']}`. Each outer fold's monitors are made from the other folds "
                      "and tested on it; the rates pool all steps. Cells: mean over seeds (min–max over the "
                      "seeds' outer folds).", "",
                      "| calibration | flag rate | × nominal | window-alarm steps / 1,000 | alarm onsets / 1,000 |",
                      "|---|---|---|---|---|"]
            for method in CALIBRATIONS:
                def cell(key, scale=1.0):
                    pooled = statistics.mean(r["pooled"][method][key] for r in far) * scale
                    each = [f["rates"][method][key] * scale for r in far for f in r["folds"]]
                    return f"{pooled:.3f} ({min(each):.3f}–{max(each):.3f})"
                lines.append(f"| {method} | {cell('flag_rate')} | {cell('flag_rate', 1 / nominal_far['flag_rate'])} | "
                             f"{cell('window_alarm_steps_per_1000')} | {cell('window_alarm_onsets_per_1000')} |")
        if first.get("detection_delay"):
            lines += ["", f"### The policy's episodes: alarms, and delay after a plant change at step "
                          f"{first['change_at']}", "",
                      "| plant | calibration | flag rate | window-alarm steps / 1,000 | episodes alarmed before "
                      "the change | detected after it | median delay (steps) |", "|---|---|---|---|---|---|---|"]
            for plant in ("nominal", *PLANTS):
                for method in ("split", "cross_fit"):
                    rates = [r["policy_alarm_rates"][plant][method] for r in records]
                    row = f"| {plant} | {method} | {_cell([x['flag_rate'] for x in rates])} | " \
                          f"{_cell([x['window_alarm_steps_per_1000'] for x in rates])} | "
                    if plant == "nominal":
                        lines.append(row + "– | – | – |")
                        continue
                    d = [r["detection_delay"][plant][method] for r in records]
                    episodes_n = sum(len(x["delays"]) for x in d)
                    found = [v for x in d for v in x["delays"] if v is not None]
                    before = sum(x["alarm_before_change"] for x in d)
                    median = f"{statistics.median(found):g}" if found else "–"
                    lines.append(row + f"{before}/{episodes_n} | {len(found)}/{episodes_n} | {median} |")
        lines.append("")
    return "\n".join(lines)


# ----------------------------------------------------------------------- main
def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="one setting and seed")
    r.add_argument("--setting", choices=sorted(SETTINGS), required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--tsidm-steps", type=int, default=3000, help="TS-IDM steps (the study budget: 3000)")
    r.add_argument("--ensemble-steps", type=int, default=3000, help="steps of the dynamics ensemble")
    r.add_argument("--folds", type=int, default=5, help="folds of the cross-fitted calibration")
    r.add_argument("--precision", choices=("fp32", "bf16"), default="fp32", help="the ensemble's training")
    r.add_argument("--window", type=int, default=100, help="the monitors' window (steps)")
    r.add_argument("--windows", type=int, nargs="+", default=[1, 10, 50, 100, 200], help="window AUROC lengths")
    r.add_argument("--replay", type=int, default=2000, help="test states replayed per shifted set")
    r.add_argument("--episodes", type=int, default=5, help="policy episodes per plant")
    r.add_argument("--change-at", type=int, default=150, help="step at which the plant changes (delay episodes)")
    r.add_argument("--policy-runs", type=Path, default=REPO / "runs" / "monitor_policies",
                   help="folder of the default recipe runs whose policies are rolled out")
    r.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    r.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    r.add_argument("--force", action="store_true", help="redo an existing result")
    f = sub.add_parser("far", help="false alarms with every trajectory held out once (outer folds)")
    f.add_argument("--setting", choices=sorted(SETTINGS), required=True)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--outer-folds", type=int, default=5)
    f.add_argument("--folds", type=int, default=5, help="folds of the cross-fitted calibration")
    f.add_argument("--ensemble-steps", type=int, default=3000)
    f.add_argument("--precision", choices=("fp32", "bf16"), default="fp32", help="the ensemble's training")
    f.add_argument("--window", type=int, default=100)
    f.add_argument("--threads", type=int, default=1)
    f.add_argument("--out", type=Path, default=RESULTS)
    f.add_argument("--force", action="store_true")
    t = sub.add_parser("table", help=f"write {repo_relative(TABLE)} from the JSONs")
    t.add_argument("--check", action="store_true", help="exit 1 if the table is not what the JSONs give")
    t.add_argument("--results", type=Path, default=RESULTS)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.command == "table":
        return write_generated(args.results / TABLE.name, render(_load(args.results), _load(args.results / "bf16")),
                               "python -m benchmarks.monitor_benchmark table", check=args.check)
    if args.command == "far":
        path = args.out / f"far_{args.setting}_seed{args.seed}.json"
        if skip_existing(path, args.force):
            return 0
        write_result(path, run_far(args), force=True)
        print(f"wrote {repo_relative(path)}")
        return 0
    path = args.out / f"{args.setting}_seed{args.seed}.json"
    if skip_existing(path, args.force):
        return 0
    result = run(args)
    write_result(path, result, force=True)
    print(render({args.setting: {"run": [result], "far": []}}))
    print(f"wrote {repo_relative(path)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
