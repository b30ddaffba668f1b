#!/bin/bash
# The GPU checks in one run, for a machine with a CUDA GPU and no internet (a lent GPU
# machine, a robot): install from the offline wheelhouse into the machine's own python3, build,
# run the GPU tests, then ./dev bench cuda's paths alone and the hot-path stages.
#
#   BUDGET=420 OUT=/tmp/gpu_check bash tools/gpu_check.sh
#
# Run from the checkout's root with .wheelhouse/ beside it (./dev wheelhouse, see
# docs/development.md). Each step runs under its own timeout and all of them within BUDGET
# seconds; a step that would start with less than 30 s left is skipped and said so. Every
# step's output goes to a file, packed after each step into OUT/results.tgz (one file to bring
# back); the summary (steps, test counts, benchmark tables) is printed on stdout. Nothing is
# piped through tee: nothing is left running when a step ends.
set -u
OUT="${OUT:-/tmp/gpu_check}"
RESULTS="$(mktemp -d)"
WHEELHOUSE="${WHEELHOUSE:-.wheelhouse}"
mkdir -p "$OUT"
START=$SECONDS

left() { echo $(( ${BUDGET:-420} - (SECONDS - START) )); }

step() {  # step NAME TIMEOUT COMMAND...
  local name=$1 limit=$2 remaining begin rc
  shift 2
  remaining=$(left)
  if [ "$remaining" -lt 30 ]; then
    echo "SKIP $name: ${remaining} s of the budget left"
    return 0
  fi
  [ "$limit" -gt "$remaining" ] && limit=$remaining
  begin=$SECONDS
  timeout -k 5 "$limit" "$@" > "$RESULTS/$name.txt" 2>&1
  rc=$?
  echo "STEP $name: rc $rc, $((SECONDS - begin)) s of $limit (at $((SECONDS - START)) s)"
  pkill -9 -f launch_free_demos.cuda_peer 2>/dev/null
  pkill -9 -f floor-consumer 2>/dev/null
  tar -C "$RESULTS" -czf "$OUT/results.tgz" .
  return 0
}

export PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
{ nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  python3 -VV; nproc
  python3 -m pip list 2>/dev/null | grep -i -E '^(torch|cupy|numpy|pytest|pytest-xdist) '
} > "$RESULTS/machine.txt" 2>&1
cat "$RESULTS/machine.txt"

step install 120 bash -c "cd '$WHEELHOUSE' && \
  python3 -m pip install --no-index --no-deps --no-compile ./*.whl"
step build 150 python3 -m pip install --no-index --no-deps --no-build-isolation -e .
XDIST="-n 8"
python3 -c 'import xdist' 2>/dev/null || XDIST=""
step gpu_tests 200 python3 -m pytest $XDIST -q -rs -p no:cacheprovider --durations=10 \
  test/test_cuda_gpu.py test/test_import_order.py test/test_cuda_backend.py \
  test/test_dlpack_export.py \
  test/test_readme.py::test_gpu_camera_and_viewer_exchange_zero_copy_tensors
tail -3 "$RESULTS/gpu_tests.txt" 2>/dev/null
step bench_cuda 150 python3 -m launch_free_demos.bench.cuda --json "$RESULTS/bench_cuda.json"
grep -E '^\||x the floor|1 KiB stock|^Targets' "$RESULTS/bench_cuda.txt" 2>/dev/null
for round in 2 3; do
  step "bench_floor_cuda_$round" 80 python3 -m launch_free_demos.bench.cuda \
    --paths floor,cuda --json "$RESULTS/bench_floor_cuda_$round.json"
  grep -E '^\| [0-9]|x the floor' "$RESULTS/bench_floor_cuda_$round.txt" 2>/dev/null
done
step hotpath 110 python3 -m launch_free_demos.bench.hotpath --frames 40 --rate 30
grep -E '^\|' "$RESULTS/hotpath.txt" 2>/dev/null
echo "DONE in $((SECONDS - START)) s; results in $OUT/results.tgz"
rm -rf "$RESULTS"
