#!/usr/bin/env bash
# The GPU check: one prepared script for a lent GPU machine (no network there), under 10 minutes.
#
#   1. installs the project from wheels carried in .whl/ (the machine's image has torch with
#      CUDA but not torchrl, tensordict, gymnasium, mujoco, hydra or minari); make them here with
#        bash benchmarks/gpu_check.sh --download
#   2. runs the tests that use CUDA (tests/test_device.py, and the CUDA-graph steps against eager in
#      tests/test_compile.py; they skip on a machine without one);
#   3. times each stage's train step eager, compiled and graph-captured (benchmarks.compile_speed,
#      the recipe's widths, one seed), and picks the fastest mode;
#   4. runs the paper's whole budget in that mode, for one seed and for five stacked seeds, each as far
#      as it gets within its cap (the table reads each stage's speed from its last progress bar).
# Everything is written under a work folder; $OUT gets GPU.md (python -m benchmarks.gpu_table) and
# one archive of the text files (the device returns at most 8 files). Commit the archive's walls.txt,
# gpu.txt, tests.txt, mode.txt, compile_speed.json and *.log under benchmarks/results/gpu/<date>/ and
# run benchmarks.gpu_table there.
#
# Device call (from the repository root; $OUT comes back):
#   bash benchmarks/gpu_check.sh            with carry: [".whl"] and timeout_s 590
# DEVICE=cpu SKIP_INSTALL=1 CAP_SCALE=0.2 bash benchmarks/gpu_check.sh  rehearses the flow on a CPU.
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
  # hydra's parser runtime is published as a source archive only; pure Python, so its wheel is built here
  python3 -m pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3
  exit $?
fi
OUT=${OUT:-/tmp/gpu_check}; mkdir -p "$OUT"
RESULT_OUT=$OUT; OUT=$(mktemp -d /tmp/gpu_check_work.XXXX)  # fresh per call: a warm machine keeps /tmp
pack() {  # the table, and every text file the runs wrote, as one archive in the returned folder
  python3 -m benchmarks.gpu_table "$OUT" > "$RESULT_OUT/GPU.md" 2>&1
  (cd "$OUT" && find . \( -name "*.json" -o -name "*.log" -o -name "*.txt" -o -name "*.md" \) -print0 \
    | tar -czf "$RESULT_OUT/gpu_check.tar.gz" --null -T -)
}
trap pack EXIT
export PYTHONUNBUFFERED=1  # no MUJOCO_GL: nothing renders, and its EGL loader is absent there
DEVICE=${DEVICE:-cuda}
cap() { python3 -c "print(max(5, round($1 * ${CAP_SCALE:-1})))"; }  # a step's time cap, in seconds
if [ -z "${SKIP_INSTALL:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl \
    || { echo "wheel install failed"; exit 1; }
  export PYTHONPATH=/tmp/site:$PWD
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader > "$OUT/gpu.txt" 2>/dev/null \
  || echo "no GPU: $DEVICE" > "$OUT/gpu.txt"
cat "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

echo "== tests that use CUDA"
timeout "$(cap 90)" python3 -m pytest -q tests/test_device.py tests/test_compile.py -k "cuda or device" 2>&1 \
  | tee "$OUT/tests.txt" | tail -5
pack  # again after each step: a call killed at its limit runs no EXIT trap

echo "== train steps per second: eager, compile, CUDA graphs"
modes="eager compile"; [ "$DEVICE" = cuda ] && modes="eager compile cudagraphs"
timeout "$(cap 160)" python3 -m benchmarks.compile_speed --device "$DEVICE" --threads 4 --warmup 30 --steps 100 \
  --repeats 3 --modes $modes --json "$OUT/compile_speed.json" > "$OUT/compile_speed.log" 2>&1
tail -12 "$OUT/compile_speed.log"
# the fastest mode over the stages timed (the smaller sum of ms per step); eager if none was
echo eager > "$OUT/mode.txt"
[ -f "$OUT/compile_speed.json" ] && python3 - "$OUT/compile_speed.json" > "$OUT/mode.txt" <<'PY'
import json, sys
stages = json.load(open(sys.argv[1]))["stages"]
modes = set.intersection(*(set(by_mode) for by_mode in stages.values()))
print(min(modes, key=lambda m: sum(by_mode[m]["ms_per_step"] for by_mode in stages.values())))
PY
pack
mode=$(cat "$OUT/mode.txt")
case "$mode" in
  compile) switches="compile.compile=true" ;;
  cudagraphs) switches="compile.cudagraphs=true" ;;
  compile+cudagraphs) switches="compile.compile=true compile.cudagraphs=true" ;;
  *) switches="" ;;
esac
echo "fastest mode: $mode"

timed() {  # timed NAME TIMEOUT recipe-overrides...: runs the recipe, records its wall seconds and exit code
  local name=$1 limit=$2; shift 2
  local start=$(date +%s)
  timeout "$limit" python3 recipes/tels_offline.py device="$DEVICE" logger.wandb_mode=disabled run_dir="$OUT/$name" \
    $switches "$@" > "$OUT/$name.log" 2>&1
  echo "$name $? $(( $(date +%s) - start ))" >> "$OUT/walls.txt"
  pack
}
echo "== the paper's whole budget: one seed, then five seeds in one process"
timed paper_seed0 "$(cap 110)" budget=paper seed=0
timed paper_seeds5 "$(cap 100)" budget=paper 'seeds=[0,1,2,3,4]'

cat "$OUT/walls.txt"
