#!/usr/bin/env bash
# The GPU check: one prepared script for a lent GPU machine (no network there), <= 8 minutes.
#
#   1. installs the project from wheels carried in .whl/ (the machine's image has torch with
#      CUDA but not torchrl, tensordict, gymnasium, mujoco, hydra or minari); make them here with
#        bash benchmarks/gpu_check.sh --download
#   2. runs the tests that use CUDA (tests/test_device.py; they skip on a machine without one);
#   3. times the study budget (3k TS-IDM + 5k policy steps) for one seed and for five seeds in one
#      process (seeds=[0,1,2,3,4], stacked), then the paper-budget run of one seed
#      (domain=paper budget=paper device=cuda), and prints a table from the runs' results.json.
#
# Device call (from the repository root; $OUT comes back):
#   bash benchmarks/gpu_check.sh            with carry: [".whl"] and timeout_s 580
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

timed() {  # timed NAME TIMEOUT recipe-overrides...: runs the recipe, records its wall seconds and exit code
  local name=$1 limit=$2; shift 2
  local start=$(date +%s)
  timeout "$limit" python3 recipes/tels_offline.py device=cuda logger.wandb_mode=disabled run_dir="$OUT/$name" "$@" \
    > "$OUT/$name.log" 2>&1
  echo "$name $? $(( $(date +%s) - start ))" >> "$OUT/walls.txt"
}
echo "== study budget: one seed, then five seeds in one process"
timed study_seed0 100 seed=0
timed study_seeds5 160 'seeds=[0,1,2,3,4]'
echo "== paper budget, one seed"
timed paper_seed0 230 domain=paper budget=paper seed=0

python3 - "$OUT" <<'PY' | tee "$OUT/table.md"
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
walls = {name: (int(rc), int(s)) for name, rc, s in (line.split() for line in (out / "walls.txt").read_text().splitlines())}
print("| run | exit | wall s (process) | stage 1 steps/s | stage 2 steps/s (no eval) | eval s | final score |")
print("|---|---|---|---|---|---|---|")
for name, label in (("study_seed0", "study budget, 1 seed"), ("study_seeds5", "study budget, 5 seeds in one process"),
                    ("paper_seed0", "paper budget, 1 seed")):
    rc, wall = walls.get(name, (None, None))
    try:
        r = json.loads((out / name / "results.json").read_text())
    except (OSError, ValueError):
        print(f"| {label} | {rc} | {wall} | did not finish | | | |")
        continue
    if "seeds" in r:  # the aggregate of a seeds run; the stage speeds are in each seed's results.json
        one = json.loads((out / name / "seed0" / "results.json").read_text())
        r = {**one, "final_normalized_score_mean": r["final_score_mean"]}
    s = r["steps_per_s"]
    print(f"| {label} | {rc} | {wall} | {s['tsidm']:.1f} | {s['policy_excluding_eval']:.1f} | "
          f"{r['wall_time_s']['eval']:.1f} | {r['final_normalized_score_mean']:.1f} |")
PY
