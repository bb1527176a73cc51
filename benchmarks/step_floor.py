"""Where the time of a TELS train step goes, and the fastest a paper-budget run could be on this CPU.

Builds both stages with the recipe's own helpers (``torchrl_tels.trainer``; paper widths,
Tables 10-11, batch 256, fused Adam, hopper-medium-v2 10k) and, with torch's thread
count pinned, prints:

- ms per phase of a policy step (value forward/backward/Adam, guide
  forward/backward/Adam, target update, buffer sample) and of a TS-IDM step,
  medians over interleaved repeats, for each precision asked for;
- the matrix-multiplication FLOPs of one step of each stage (torch profiler)
  and the best rate this CPU reaches on the step's largest product
  (256x1024 @ 1024x1024), hence a floor for the paper-budget run (Table 10:
  1000 epochs; Table 11: 100k steps) that no removal of overhead can beat.

    python -m benchmarks.step_floor --threads 2

The configuration is the recipe's default (``recipes/config``); ``--override guide.alpha=0.01``
(any hydra override of the recipe) times another one.

A precision this CPU does not multiply natively (bf16 without AVX512-BF16/AMX)
is timed over ``--emulated-steps`` steps only: it is tens of times slower.
"""
from __future__ import annotations

import argparse
import math
import statistics
import time

import torch
from torch.profiler import profile, ProfilerActivity

from benchmarks.harness import recipe_config
from torchrl_tels.config import native_bf16_supported
from torchrl_tels.data import load_dataset, make_offline_replay_buffer
from torchrl_tels.trainer import make_stage2, make_tsidm, make_tsidm_loss
from torchrl_tels.training import sum_losses

MATMULS = ("aten::mm", "aten::addmm", "aten::bmm")


def make_stages(cfg, data):
    """The recipe's two steps, built by its own helpers, as closures that add ms per phase to a dict."""
    tsidm = make_tsidm(cfg, data)
    beta = 1.0 if cfg.tsidm.beta == "auto" else float(cfg.tsidm.beta)
    tsidm_loss = make_tsidm_loss(cfg, tsidm, beta)
    tsidm_optim = torch.optim.Adam(tsidm_loss.parameters(), lr=cfg.tsidm.lr, fused=True)
    tsidm_buffer = make_offline_replay_buffer(data, cfg.tsidm.batch_size)
    stage2 = make_stage2(cfg, data, make_tsidm(cfg, data), action_spec=None)
    buffer, target = stage2.buffer, stage2.target_updater
    value_loss, value_optim = stage2.value_loss, stage2.value_optim
    guide_loss, guide_optim = stage2.guide_loss, stage2.guide_optim

    def timed(times, name, start):
        now = time.perf_counter()
        times[name] = times.get(name, 0.0) + 1e3 * (now - start)
        return now

    def train_phase(times, prefix, loss, optim, batch, precision, t):
        # forward under the recipe's autocast, backward of the loss_* sum, Adam: each timed on its own
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            losses = loss(batch)
        t = timed(times, f"{prefix}forward", t)
        optim.zero_grad()
        sum_losses(losses).backward()
        t = timed(times, f"{prefix}backward", t)
        optim.step()
        return timed(times, f"{prefix}adam", t)

    def tsidm_step(times, precision):
        t = time.perf_counter()
        batch = tsidm_buffer.sample()
        t = timed(times, "sample", t)
        train_phase(times, "", tsidm_loss, tsidm_optim, batch, precision, t)

    def policy_step(times, precision):
        t = time.perf_counter()
        batch = buffer.sample()
        t = timed(times, "sample", t)
        t = train_phase(times, "value_", value_loss, value_optim, batch, precision, t)
        t = train_phase(times, "guide_", guide_loss, guide_optim, batch, precision, t)
        target.step()
        timed(times, "target_update", t)

    return {"tsidm": tsidm_step, "policy": policy_step}


def matmul_gflop_per_step(step) -> float:
    """GFLOP of the matrix products in one fp32 step, as the torch profiler counts them."""
    step({}, "fp32")
    with profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
        step({}, "fp32")
    return sum(e.flops for e in prof.key_averages() if e.key in MATMULS) / 1e9


def best_matmul_gflops(repeats: int) -> float:
    """fp32 rate of the step's largest product, 256x1024 @ 1024x1024 (h_inv, V and pi_g hidden layers)."""
    a, w = torch.randn(256, 1024), torch.randn(1024, 1024)
    for _ in range(20):
        a @ w
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(50):
            a @ w
        rates.append(50 * 2 * 256 * 1024 * 1024 / (time.perf_counter() - start) / 1e9)
    return max(rates)


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20, help="steps per timed block")
    parser.add_argument("--emulated-steps", type=int, default=3, help="steps per block for emulated bf16")
    parser.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    parser.add_argument("--override", nargs="*", default=[], help="hydra overrides of the recipe's config")
    args = parser.parse_args()
    cfg = recipe_config(args.override)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    native = native_bf16_supported()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}, native bf16: {native}; paper widths, batch 256, "
          f"alpha {cfg.guide.alpha:g}, hopper-medium-v2 10k; median of {args.repeats} interleaved blocks")
    stages = make_stages(cfg, load_dataset("hopper-medium-v2-10k"))

    def steps_for(precision):
        return args.steps if precision == "fp32" or native else args.emulated_steps

    for stage, step in stages.items():
        for precision in args.precisions:
            step({}, precision)  # warm-up: oneDNN picks its kernels on the first call
        blocks = {p: [] for p in args.precisions}
        for _ in range(args.repeats):
            for precision in args.precisions:
                times, n = {}, steps_for(precision)
                start = time.perf_counter()
                for _ in range(n):
                    step(times, precision)
                times["total"] = 1e3 * (time.perf_counter() - start)
                blocks[precision].append({k: v / n for k, v in times.items()})
        print(f"\n{stage} step, ms{' (bf16 emulated)' if 'bf16' in args.precisions and not native else ''}")
        phases = list(blocks[args.precisions[0]][0])
        print(f"{'phase':<16}" + "".join(f"{p:>12}" for p in args.precisions))
        for phase in phases:
            print(f"{phase:<16}" + "".join(
                f"{statistics.median(b[phase] for b in blocks[p]):>12.2f}" for p in args.precisions))
        if "fp32" in blocks and "bf16" in blocks:
            ratio = statistics.median(b["total"] for b in blocks["bf16"]) / statistics.median(
                b["total"] for b in blocks["fp32"])
            print(f"bf16 / fp32 time per step: {ratio:.2f}x")

    gflops = best_matmul_gflops(args.repeats)
    tsidm_steps, policy_steps = 1000 * math.ceil(9013 / 256), 100_000  # Table 10, Table 11
    work = {stage: matmul_gflop_per_step(step) for stage, step in stages.items()}
    floor = {"tsidm": tsidm_steps * work["tsidm"] / gflops / 60, "policy": policy_steps * work["policy"] / gflops / 60}
    print(f"\nbest fp32 rate on 256x1024 @ 1024x1024: {gflops:.0f} GFLOP/s")
    for stage, steps in (("tsidm", tsidm_steps), ("policy", policy_steps)):
        print(f"{stage}: {work[stage]:.2f} GFLOP of matrix products per step x {steps} steps "
              f"= at least {floor[stage]:.1f} min")
    print(f"floor of the paper-budget run in fp32 (matrix products only, no evaluation): "
          f"{floor['tsidm'] + floor['policy']:.1f} min")


if __name__ == "__main__":
    main()
