#!/usr/bin/env bash
# The GPU check: one prepared script for a lent GPU machine (no network there), <= 8 minutes.
#
#   1. installs the project from wheels carried in .whl/ (the machine's image has torch with
#      CUDA but not torchrl, tensordict, gymnasium, mujoco, hydra or minari); make them here with
#        bash benchmarks/gpu_check.sh --download
#   2. runs the tests that use CUDA (tests/test_device.py; they skip on a machine without one);
#   3. times the study budget (3k TS-IDM + 5k policy steps) for one seed and for five seeds in one
#      process (seeds=[0,1,2,3,4], stacked), and prints a table from the runs' results.json;
#   4. runs stage 1 alone for the paper's 36k TS-IDM steps (benchmarks.reproduction.latent_shrink,
#      seed 1, free and standardized latents side by side, each TS-IDM saved for a stage 2 run here).
# Everything is written under a work folder; $OUT gets table.md and one archive of the text files
# (the device returns at most 8 files).
#
# Device call (from the repository root; $OUT comes back):
#   bash benchmarks/gpu_check.sh            with carry: [".whl"] and timeout_s 590
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
RESULT_OUT=$OUT; OUT=/tmp/gpu_check_work; mkdir -p "$OUT"
pack() {  # the table and every text file the runs wrote, as one archive in the returned folder
  cp "$OUT/table.md" "$RESULT_OUT/" 2>/dev/null
  (cd "$OUT" && find . \( -name "*.json" -o -name "*.log" -o -name "*.txt" -o -name "*.md" \) -print0 \
    | tar -czf "$RESULT_OUT/gpu_check.tar.gz" --null -T -)
  [ -d "$OUT/tsidm" ] && tar -cf "$RESULT_OUT/tsidm.tar" -C "$OUT" tsidm  # about 7 MB per TS-IDM
}
trap pack EXIT
export PYTHONUNBUFFERED=1 MUJOCO_GL=egl
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl \
  || { echo "wheel install failed"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

echo "== tests that use CUDA"
timeout 80 python3 -m pytest -q tests/test_device.py 2>&1 | tee "$OUT/tests.txt" | tail -5

timed() {  # timed NAME TIMEOUT recipe-overrides...: runs the recipe, records its wall seconds and exit code
  local name=$1 limit=$2; shift 2
  local start=$(date +%s)
  timeout "$limit" python3 recipes/tels_offline.py device=cuda logger.wandb_mode=disabled run_dir="$OUT/$name" "$@" \
    > "$OUT/$name.log" 2>&1
  echo "$name $? $(( $(date +%s) - start ))" >> "$OUT/walls.txt"
}
echo "== study budget: one seed, then five seeds in one process"
timed study_seed0 120 seed=0
timed study_seeds5 150 'seeds=[0,1,2,3,4]'

python3 - "$OUT" <<'PY' | tee "$OUT/table.md"
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
walls = {name: (int(rc), int(s)) for name, rc, s in (line.split() for line in (out / "walls.txt").read_text().splitlines())}
print("| run | exit | wall s (process) | stage 1 steps/s | stage 2 steps/s (no eval) | eval s | final score |")
print("|---|---|---|---|---|---|---|")
for name, label in (("study_seed0", "study budget, 1 seed"), ("study_seeds5", "study budget, 5 seeds in one process")):
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

echo "== stage 1 alone at the paper's 36k TS-IDM steps, seed 1 (free and standardized latents at once)"
for option in free standardized; do
  ( start=$(date +%s)
    timeout 180 python3 -m benchmarks.reproduction.latent_shrink --steps 36000 --seed 1 --options $option --force \
      --tsidm-dir "$OUT/tsidm" \
      > "$OUT/shrink_$option.log" 2>&1
    echo "shrink_$option $? $(( $(date +%s) - start ))" >> "$OUT/walls.txt" ) &
done
wait
mkdir -p "$OUT/latent_shrink"
cp -r benchmarks/reproduction/results/latent_shrink/*/ "$OUT/latent_shrink/" 2>/dev/null
cat "$OUT/walls.txt"
