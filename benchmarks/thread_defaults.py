"""Stage-1 speed under each CPU thread setting, alone and beside a busy neighbour process.

A TS-IDM train step at Table 10's widths (hopper sizes, batch 256, forward + backward +
fused Adam) runs in a fresh subprocess per measurement, since OpenMP reads its settings
once, when torch starts. Settings: torch's default thread count (every core), the same with
``OMP_WAIT_POLICY=PASSIVE`` (idle OpenMP threads sleep instead of spinning), 1 thread, and
the recipe's default (``threads=auto``: half the logical CPUs, with PASSIVE).
With ``--neighbour``, each measurement is repeated beside a process that keeps one core
busy with single-thread matrix products, as a second run on a shared machine does.
Settings alternate, each repeated; the script prints the median steps/s per setting and
condition, and the slowdown the neighbour causes.

    python -m benchmarks.thread_defaults --repeats 3 --neighbour
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

from torchrl_tels.config import resolve_threads

PASSIVE = {"OMP_WAIT_POLICY": "PASSIVE"}
#: name -> (environment additions, torch threads or None for torch's default)
SETTINGS = {
    "torch's default": ({}, None),
    "torch's default, OMP_WAIT_POLICY=PASSIVE": (PASSIVE, None),
    "1 thread": ({}, 1),
    "the recipe's default: threads=auto, PASSIVE": (PASSIVE, resolve_threads("auto")),
}

WORKER = """
import sys, time, torch
from tensordict import TensorDict
from torchrl_tels.modules import TSIDM
from torchrl_tels.objectives import TSIDMLoss
from torchrl_tels.training import sum_losses
threads, seconds = (None if sys.argv[1] == "None" else int(sys.argv[1])), float(sys.argv[2])
if threads:
    torch.set_num_threads(threads)
torch.manual_seed(0)
tsidm = TSIDM(11, 3)
loss = TSIDMLoss(tsidm, beta=1.0, check_inputs=False)
optim = torch.optim.Adam(loss.parameters(), lr=3e-4, fused=True)
obs = torch.randn(256, 11)
batch = TensorDict({"observation": obs, "action": torch.rand(256, 3) * 2 - 1,
                    ("next", "observation"): obs + 0.1 * torch.randn(256, 11)}, [256])
def step():
    optim.zero_grad()
    sum_losses(loss(batch)).backward()
    optim.step()
for _ in range(5):
    step()
start, steps = time.perf_counter(), 0
while time.perf_counter() - start < seconds:
    step()
    steps += 1
print(steps / (time.perf_counter() - start), torch.get_num_threads())
"""

NEIGHBOUR = """
import torch
torch.set_num_threads(1)
a = torch.randn(512, 512)
while True:
    a = torch.tanh(a @ a)
"""


def measure(name: str, seconds: float) -> tuple[float, int]:
    extra, threads = SETTINGS[name]
    env = {**os.environ, **extra}
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(key, None)  # the setting under test decides, not the caller's shell
    out = subprocess.run([sys.executable, "-c", WORKER, str(threads), str(seconds)], env=env,
                         capture_output=True, text=True, check=True)
    rate, used = out.stdout.split()
    return float(rate), int(used)


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=10.0, help="timed seconds per measurement")
    parser.add_argument("--neighbour", action="store_true", help="also measure beside a busy 1-thread process")
    args = parser.parse_args()

    conditions = ["alone", "beside a busy neighbour"] if args.neighbour else ["alone"]
    rates = {(name, c): [] for name in SETTINGS for c in conditions}
    threads_used = {}
    for _ in range(args.repeats):
        for condition in conditions:
            neighbour = None
            if condition != "alone":
                env = {**os.environ, "OMP_NUM_THREADS": "1"}
                neighbour = subprocess.Popen([sys.executable, "-c", NEIGHBOUR], env=env)
                time.sleep(2.0)
            try:
                for name in SETTINGS:
                    rate, threads_used[name] = measure(name, args.seconds)
                    rates[name, condition].append(rate)
            finally:
                if neighbour is not None:
                    neighbour.kill()
                    neighbour.wait()
    print(f"TS-IDM train steps/s (Table 10 widths, hopper sizes, batch 256), median of {args.repeats}; "
          f"{os.cpu_count()} logical CPUs")
    print("| setting | torch threads | " + " | ".join(conditions) + (" | slowdown |" if args.neighbour else " |"))
    print("|---|---|" + "---|" * (len(conditions) + int(args.neighbour)))
    for name in SETTINGS:
        medians = [statistics.median(rates[name, c]) for c in conditions]
        row = f"| {name} | {threads_used[name]} | " + " | ".join(f"{m:.2f}" for m in medians)
        if args.neighbour:
            row += f" | {medians[0] / medians[1]:.2f}x"
        print(row + " |")


if __name__ == "__main__":
    main()
