"""Export a finished TELS run as standalone torch.export programs (the actor, and the consistency monitor).

    python recipes/export_policy.py runs/a                      # runs/a/export/policy.pt2 (+ monitor.pt2)
    python recipes/export_policy.py runs/a --out deploy/ --onnx  # also policy.onnx / monitor.onnx
    python recipes/export_policy.py runs/a --calibrate hopper-medium-v2-10k   # calibrate the monitor here

``policy.pt2`` maps observations (B, obs_dim, float32) to actions by Eq. (11), with the run's
state normalization, latent standardization, re-encoding option and clipping to the action
bounds. ``monitor.pt2`` maps (observation, action, next observation) to the monitor's score
and ``ood`` flag; it is written when the run folder holds a calibrated ``monitor.pt`` (the
recipe saves one) or ``--calibrate DATASET`` is given. Both load with torch alone:
``torch.export.load("runs/a/export/policy.pt2").module()``. ``export.json`` records the sizes,
bounds, threshold and the checkpoints' SHA-256.

A folder that is not a finished run (no ``results.json``), a missing ``tsidm.pt``/``policy.pt``
or checkpoints from different runs stop the export with one ``error:`` line (exit code 2),
and nothing is written.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from torchrl_tels.errors import TelsError
from torchrl_tels.export import export_run


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="the folder of a finished run of recipes/tels_offline.py")
    parser.add_argument("--out", default=None, help="output folder (default: RUN_DIR/export)")
    parser.add_argument("--onnx", action="store_true", help="also write ONNX files (needs onnx and onnxscript)")
    parser.add_argument("--calibrate", default=None, metavar="DATASET",
                        help="calibrate the monitor on this dataset (a load_dataset name or path)")
    parser.add_argument("--quantile", type=float, default=0.99, help="calibration quantile (default 0.99)")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        written = export_run(args.run_dir, args.out, onnx=args.onnx, calibrate=args.calibrate,
                             quantile=args.quantile)
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path in written.values():
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
