"""How long does drawing a batch from the offline replay buffer take?

Times, in microseconds per call, on the hopper-medium-v2 10k dataset at batch
size 256:

* ``rb.sample()`` of :func:`torchrl_tels.data.make_offline_replay_buffer`
  (uniform random and without-replacement samplers);
* indexing the dataset TensorDict directly (``data[idx]``);
* a plain ``index_select`` on one tensor holding every field side by side,
  the fastest a batch can possibly be drawn;
* for scale, one Adam step of a small 2x256 MLP regressing actions on
  observations at the same batch size (the cheapest training step any
  TELS component takes).

Each method is timed over ``--calls`` calls, the methods are interleaved
``--repeats`` times, and the median over repeats is printed. Torch is pinned to
one thread so the figures do not depend on what else runs on the machine.

Usage::

    python -m benchmarks.replay_buffer_sampling [--repeats 7] [--calls 200]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
from torch import nn

from torchrl_tels.data import load_dataset, make_offline_replay_buffer

BATCH_SIZE = 256


def time_per_call(fn: Callable[[], object], calls: int) -> float:
    """Mean wall time of ``fn`` over ``calls`` calls, in microseconds."""
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--calls", type=int, default=200)
    args = parser.parse_args()

    torch.set_num_threads(1)
    torch.manual_seed(0)
    data = load_dataset("hopper-medium-v2-10k")
    num_transitions = len(data)

    rb_random = make_offline_replay_buffer(data, BATCH_SIZE, seed=0)
    rb_no_replacement = make_offline_replay_buffer(
        data, BATCH_SIZE, sampler="without_replacement", seed=0
    )
    # Every float/bool leaf side by side in one (N, D) tensor.
    flat = torch.cat(
        [leaf.reshape(num_transitions, -1).float() for leaf in data.values(True, True)],
        dim=1,
    )

    def index_select() -> torch.Tensor:
        idx = torch.randint(num_transitions, (BATCH_SIZE,))
        return flat.index_select(0, idx)

    def tensordict_index():
        return data[torch.randint(num_transitions, (BATCH_SIZE,))]

    obs_dim, act_dim = data["observation"].shape[-1], data["action"].shape[-1]
    mlp = nn.Sequential(
        nn.Linear(obs_dim, 256),
        nn.ReLU(),
        nn.Linear(256, 256),
        nn.ReLU(),
        nn.Linear(256, act_dim),
    )
    optimizer = torch.optim.Adam(mlp.parameters(), lr=1e-3)
    batch = rb_random.sample()

    def mlp_step() -> None:
        loss = (mlp(batch["observation"]) - batch["action"]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    methods: dict[str, Callable[[], object]] = {
        "rb.sample() random": rb_random.sample,
        "rb.sample() without_replacement": rb_no_replacement.sample,
        "TensorDict data[idx]": tensordict_index,
        "tensor index_select (baseline)": index_select,
        "MLP 2x256 Adam step (reference)": mlp_step,
    }
    for fn in methods.values():  # warm-up: allocator, lazy inits
        time_per_call(fn, 20)

    timings: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(args.repeats):
        for name, fn in methods.items():
            timings[name].append(time_per_call(fn, args.calls))

    medians = {name: statistics.median(values) for name, values in timings.items()}
    baseline = medians["tensor index_select (baseline)"]
    print(
        f"torch {torch.__version__}, torch.get_num_threads() = "
        f"{torch.get_num_threads()} (pinned to 1)"
    )
    print(
        f"dataset hopper-medium-v2-10k: {num_transitions} transitions, batch "
        f"{BATCH_SIZE}; median of {args.repeats} interleaved repeats x "
        f"{args.calls} calls"
    )
    print(f"{'method':34s} {'us/call':>10s} {'x baseline':>11s}")
    for name, median in medians.items():
        print(f"{name:34s} {median:10.1f} {median / baseline:11.1f}")


if __name__ == "__main__":
    main()
