"""One full TS-IDM train step: forward-mode JVPs vs per-sample ``vmap(jacrev)`` Jacobians.

Both variants compute the same Eq. (3)-(7) losses (checked at start-up), with
Table 10's widths, batch 256, forward + backward + Adam (fused, as the
recipe uses). They alternate in one
process with torch's thread count pinned, and the script prints median ms/step
and the ratio for hopper (11/3) and walker2d (17/6) sizes.

    python -m benchmarks.tsidm_step --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict

from torchrl_tels.modules import TSIDM
from torchrl_tels.objectives import TSIDMLoss
from torchrl_tels.training import sum_losses


def jvp_via_vmap_jacrev(function, primal, tangent):
    """TSRL's way: materialize each sample's Jacobian, then multiply."""
    jacobians = torch.func.vmap(torch.func.jacrev(function))(primal)
    return function(primal), torch.einsum("boi,bi->bo", jacobians, tangent)


class JacrevTSIDMLoss(TSIDMLoss):
    jvp = staticmethod(jvp_via_vmap_jacrev)


def make_step(loss_cls, tsidm, batch):
    loss = loss_cls(tsidm, beta=1.0)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4, fused=True)

    def step():
        out = loss(batch)
        optim.zero_grad()
        sum_losses(out).backward()
        optim.step()

    return loss, step


def bench(obs_dim, act_dim, batch_size, steps, repeats):
    tsidm = TSIDM(obs_dim, act_dim)
    batch = TensorDict(
        {
            "observation": torch.randn(batch_size, obs_dim),
            "action": torch.randn(batch_size, act_dim),
            ("next", "observation"): torch.randn(batch_size, obs_dim),
        },
        [batch_size],
    )
    # Same numbers from both before timing (dropout off for the comparison).
    tsidm.eval()
    with torch.no_grad():
        a = TSIDMLoss(tsidm)(batch)["ell_total"]
        b = JacrevTSIDMLoss(tsidm)(batch)["ell_total"]
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    tsidm.train()

    _, jvp_step = make_step(TSIDMLoss, tsidm, batch)
    _, jacrev_step = make_step(JacrevTSIDMLoss, tsidm, batch)
    for fn in (jvp_step, jacrev_step):  # warm-up
        fn()
    times = {"jvp": [], "vmap_jacrev": []}
    for _ in range(repeats):
        for name, fn in (("jvp", jvp_step), ("vmap_jacrev", jacrev_step)):
            start = time.perf_counter()
            for _ in range(steps):
                fn()
            times[name].append((time.perf_counter() - start) / steps * 1e3)
    return {name: statistics.median(values) for name, values in times.items()}


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=10, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved blocks per variant")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(
        f"TS-IDM train step, Table 10 widths, batch {args.batch_size}, "
        f"torch {torch.__version__}, torch threads pinned to {torch.get_num_threads()}, "
        f"median of {args.repeats} interleaved blocks of {args.steps} steps"
    )
    print(f"{'dims (obs/act)':<22}{'JVP ms/step':>14}{'vmap(jacrev) ms/step':>24}{'ratio':>8}")
    for name, obs_dim, act_dim in (("hopper", 11, 3), ("walker2d", 17, 6)):
        result = bench(obs_dim, act_dim, args.batch_size, args.steps, args.repeats)
        ratio = result["vmap_jacrev"] / result["jvp"]
        print(
            f"{name + f' ({obs_dim}/{act_dim})':<22}{result['jvp']:>14.1f}"
            f"{result['vmap_jacrev']:>24.1f}{ratio:>7.2f}x"
        )


if __name__ == "__main__":
    main()
