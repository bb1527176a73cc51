#!/usr/bin/env bash
# The GPU check: one prepared script for a lent GPU machine (no network there), <= 8 minutes.
#
#   1. installs the project from wheels carried in .whl/ (the machine's image has torch with
#      CUDA but not torchrl, tensordict, gymnasium, mujoco, hydra or minari); make them here with
#        bash benchmarks/gpu_check.sh --download
#   2. runs the tests that use CUDA (tests/test_device.py; they skip on a machine without one);
#   3. times the paper-budget run of one seed (domain=paper budget=paper device=cuda) and prints
#      a table with the stage speeds the run wrote to results.json.
#
# Device call (from the repository root; $OUT comes back):
#   bash benchmarks/gpu_check.sh            with carry: [".whl"] and timeout_s 540
# Several seeds in one process are not implemented yet, so their row stays "not measured".
# Not yet run on a GPU machine: no session so far was lent one.
set -uo pipefail
cd "$(dirname "$0")/.."
WHEELS="torchrl==0.14.1 tensordict==0.14.3 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.13.0 gymnasium==1.4.0
farama-notifications==0.0.6 cloudpickle==3.1.3 mujoco==4.0.1 mujoco-core==4.0.1 mujoco-studio==4.0.1
mujoco-studio-wasm==4.0.1 glfw==2.11.0 pyopengl==3.1.10 websockets==17.4 hydra-core==1.3.8 omegaconf==2.3.1
minari==0.5.4 typer==0.29.2 shellingham==1.5.4 annotated-doc==0.0.7"
if [ "${1:-}" = "--download" ]; then
  grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo "/.whl/" >> .git/info/exclude
  python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl $WHEELS || exit 1
  # hydra's parser runtime is published as a source archive only; pure Python, built there offline
  python3 -m pip download --no-deps --no-binary=:all: -d .whl antlr4-python3-runtime==4.9.3
  exit $?
fi
OUT=${OUT:-/tmp/gpu_check}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MUJOCO_GL=egl
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl .whl/*.tar.gz \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

echo "== tests that use CUDA"
timeout 150 python3 -m pytest -q tests/test_device.py 2>&1 | tee "$OUT/tests.txt" | tail -5

echo "== paper budget, one seed"
start=$(date +%s)
timeout 300 python3 recipes/tels_offline.py domain=paper budget=paper device=cuda seed=0 \
  run_dir="$OUT/paper_seed0" logger.wandb_mode=disabled > "$OUT/paper_seed0.log" 2>&1
rc=$?
end=$(date +%s)
python3 - "$OUT/paper_seed0/results.json" "$((end - start))" "$rc" <<'PY' | tee "$OUT/table.md"
import json, sys
path, wall, rc = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
print("| measurement | value |\n|---|---|")
try:
    r = json.load(open(path))
    print(f"| paper budget, 1 seed, wall time | {wall} s |")
    print(f"| stage 1 steps/s | {r['steps_per_s']['tsidm']:.1f} |")
    print(f"| stage 2 steps/s (without evaluation) | {r['steps_per_s']['policy_excluding_eval']:.1f} |")
    print(f"| evaluation, total | {r['wall_time_s']['eval']:.1f} s |")
    print(f"| final score | {r['final_normalized_score_mean']:.1f} |")
except (OSError, KeyError, ValueError) as err:
    print(f"| paper budget, 1 seed | did not finish (exit {rc}, {wall} s): {type(err).__name__} |")
print("| paper budget, 5 seeds in one process | not measured (not implemented) |")
PY
