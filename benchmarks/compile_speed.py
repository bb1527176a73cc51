"""Train steps per second of each stage, eager against ``torch.compile`` against CUDA graphs.

Builds both stages with the recipe's own helpers (``torchrl_tels.trainer``: the config the recipe
composes, hopper-medium-v2 10k, batch 256) once per mode, from the same seed, and times the step the
recipe's loop runs: a replay-buffer sample, the whole compiled-or-not train step (losses, backward,
Adam, target update) and the NaN watch. The modes alternate block by block after each one's warm-up
(compilation and graph capture are reported apart, as ``warm-up s``), and the table gives the median
over the blocks, with the device synchronized at each block's end.

    python -m benchmarks.compile_speed --threads 1                    # the recipe's widths, on the CPU
    python -m benchmarks.compile_speed --threads 1 --width 16         # every network 16 wide: the overhead
    python -m benchmarks.compile_speed --device cuda --seeds 5        # five stacked seeds on a GPU

``--width 16`` shrinks every network to one hidden layer of 16 units, so that arithmetic costs
nothing and what is left is the per-step overhead of Python, tensordict and kernel launches: the
figure that predicts a GPU's. CUDA graphs are timed only on a CUDA device. ``--json`` writes the
figures for ``benchmarks/gpu_table.py``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from benchmarks.harness import machine_description, recipe_config
from torchrl_tels.compile import capturable_adam
from torchrl_tels.data import load_dataset, make_offline_replay_buffer
from torchrl_tels.seeds import SeedRNG, StackedLoss
from torchrl_tels.trainer import (compile_options, make_compiled_step, make_stage2, make_tsidm, make_tsidm_loss,
                                  sample_seeds, StackedStage2)
from torchrl_tels.training import FiniteWatch

MODES = {"eager": [], "compile": ["compile.compile=true"], "cudagraphs": ["compile.cudagraphs=true"],
         "compile+cudagraphs": ["compile.compile=true", "compile.cudagraphs=true"]}
TSIDM_CELLS = ("encoder_cells", "decoder_cells", "inverse_cells", "action_decoder_cells", "dynamics_cells")


def width_overrides(width: int | None) -> list[str]:
    if width is None:
        return []
    return [f"tsidm.{name}=[{width}]" for name in TSIDM_CELLS] + [f"value.num_cells=[{width}]",
                                                                   f"guide.num_cells=[{width}]"]


def tsidm_step(cfg, data, seeds: list[int]):
    """Stage 1's loop body (``torchrl_tels.run.fit_tsidm``, one seed or stacked) as a function of nothing."""
    device = torch.device(cfg.device)
    rng = SeedRNG(len(seeds))
    losses, buffers = [], []
    for k, seed in enumerate(seeds):
        rng.start(k, seed)
        with rng.use(k):
            losses.append(make_tsidm_loss(cfg, make_tsidm(cfg, data).to(device), 0.01))
            buffers.append(make_offline_replay_buffer(data, cfg.tsidm.batch_size, device=device))
    loss = losses[0] if len(seeds) == 1 else StackedLoss(losses)
    params = loss.parameters() if len(seeds) == 1 else loss.trainable()
    optim = capturable_adam(params, lr=cfg.tsidm.lr, capturable=compile_options(cfg)["cudagraphs"])
    train_step = make_compiled_step(loss, optim, cfg)
    watch = FiniteWatch("stage 1")
    state = {"step": 0}

    def step():
        batch = buffers[0].sample() if len(seeds) == 1 else sample_seeds(buffers, rng)
        watch.update(train_step(batch), state["step"])
        state["step"] += 1

    return step


def policy_step(cfg, data, seeds: list[int]):
    """Stage 2's loop body (the recipe's ``stage2.update(stage2.sample(), step)``) as a function of nothing."""
    tsidm = make_tsidm(cfg, data)
    if len(seeds) == 1:
        stage2 = make_stage2(cfg, data, tsidm, action_spec=None)
        sample = stage2.buffer.sample
    else:
        rng = SeedRNG(len(seeds))
        stages = []
        for k, seed in enumerate(seeds):
            rng.start(k, seed)
            with rng.use(k):
                stages.append(make_stage2(cfg, data, tsidm, action_spec=None))
        stage2 = StackedStage2(stages, rng, labels=[f"seed {seed}" for seed in seeds])
        sample = stage2.sample
    state = {"step": 0}

    def step():
        stage2.update(sample(), state["step"])
        state["step"] += 1

    return step


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_block(step, steps: int, device: torch.device) -> float:
    synchronize(device)
    start = time.perf_counter()
    for _ in range(steps):
        step()
    synchronize(device)
    return 1e3 * (time.perf_counter() - start) / steps


def print_profile(stage: str, mode: str, step, steps: int, device: torch.device, rows: int = 15) -> None:
    """The operators (and compiled graphs) that take a step's time, by self time per step."""
    from torch.profiler import profile, ProfilerActivity

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        time_block(step, steps, device)
    events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events)
    print(f"\n{stage} step, {mode}: self CPU time per step by operator (profiled, so slower than timed)")
    for event in events[:rows]:
        print(f"  {event.key[:60]:60s} {event.self_cpu_time_total / steps / 1e3:7.3f} ms "
              f"{event.count / steps:6.1f} calls")
    print(f"  {'total':60s} {total / steps / 1e3:7.3f} ms")


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--width", type=int, default=None, help="every hidden layer this wide (one layer)")
    parser.add_argument("--seeds", type=int, default=1, help="stacked seeds per step")
    parser.add_argument("--modes", nargs="+", default=None, choices=list(MODES),
                        help="default: eager and compile, plus cudagraphs and compile+cudagraphs on CUDA")
    parser.add_argument("--stages", nargs="+", default=["tsidm", "policy"], choices=["tsidm", "policy"])
    parser.add_argument("--warmup", type=int, default=30, help="steps before timing (compilation, capture)")
    parser.add_argument("--steps", type=int, default=100, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=5, help="timed blocks per mode, interleaved")
    parser.add_argument("--precision", default="fp32", choices=["fp32", "bf16"])
    parser.add_argument("--override", nargs="*", default=[], help="more hydra overrides of the recipe's config")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--profile", action="store_true",
                        help="after timing, profile one block per stage and mode: where a step's time goes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    modes = args.modes or (list(MODES) if device.type == "cuda" else ["eager", "compile"])
    seeds = list(range(args.seeds))
    data = load_dataset("hopper-medium-v2-10k")
    common = [f"device={args.device}", f"precision={args.precision}", *width_overrides(args.width), *args.override]
    machine = machine_description()
    if device.type == "cuda":
        machine["gpu"] = torch.cuda.get_device_name(device)
    widths = f"{args.width} units" if args.width else "the recipe's widths (Tables 10-11)"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {machine.get('gpu') or machine['cpu']}, "
          f"{args.precision}, {widths}, batch 256, {len(seeds)} seed(s); median of {args.repeats} interleaved "
          f"blocks of {args.steps} steps after {args.warmup} warm-up steps")
    figures = {"machine": machine, "args": {k: str(v) for k, v in vars(args).items()}, "stages": {}}
    builders = {"tsidm": tsidm_step, "policy": policy_step}
    for stage in args.stages:
        steps, warmup_s, blocks = {}, {}, {mode: [] for mode in modes}
        for mode in modes:
            cfg = recipe_config(common + MODES[mode])
            torch.manual_seed(0)
            steps[mode] = builders[stage](cfg, data, seeds)
            synchronize(device)
            start = time.perf_counter()
            for _ in range(args.warmup):
                steps[mode]()
            synchronize(device)
            warmup_s[mode] = time.perf_counter() - start
        for _ in range(args.repeats):
            for mode in modes:
                blocks[mode].append(time_block(steps[mode], args.steps, device))
        ms = {mode: statistics.median(blocks[mode]) for mode in modes}
        figures["stages"][stage] = {mode: {"ms_per_step": ms[mode], "steps_per_s": 1e3 / ms[mode],
                                           "warmup_s": warmup_s[mode], "blocks_ms": blocks[mode]} for mode in modes}
        print(f"\n{stage} step       ms/step   steps/s  vs eager  warm-up s")
        for mode in modes:
            ratio = f"{ms['eager'] / ms[mode]:8.2f}x" if "eager" in ms else "       -"
            print(f"{mode:18s} {ms[mode]:8.2f} {1e3 / ms[mode]:9.1f} {ratio} {warmup_s[mode]:10.1f}")
        if args.json:  # after each stage, so that a run stopped at a time cap keeps what it measured
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(figures, indent=2))
        if args.profile:
            for mode in modes:
                print_profile(stage, mode, steps[mode], args.steps, device)


if __name__ == "__main__":
    main()
