#!/usr/bin/env bash
# The GPU checks and benchmarks in one go, for a CUDA host without a package registry (a
# benchmark host): builds the extensions in place, runs the gpu-marked tests, then the benchmarks.
#   tests/gpu_suite.sh tests CORPUS_DIR   # gpu tests only
#   tests/gpu_suite.sh bench CORPUS_DIR   # navi bench trace / env / train (+ the learner anchor if present)
#   tests/gpu_suite.sh all CORPUS_DIR     # both, in one job
# Needs torch (CUDA), numpy, nvcc, pybind11, setuptools, typer; pytest may come from artifacts/pytest-vendor.
set -euo pipefail
cd "$(dirname "$0")/.."
what=${1:-tests}; corpus=${2:-artifacts/bench-corpus}
out=${OUT:-artifacts/gpu-suite}; mkdir -p "$out"
source tests/gpu_env.sh
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
if [ "$what" = tests ] || [ "$what" = all ]; then
  # Every gpu-marked test under tests/, selected by the marker. NAVI_GPU_ONLY=1 leaves out the modules
  # with no gpu mark, which may import what a benchmark host lacks (tests/test_gpu_suite.py checks that
  # this selects the same tests as `pytest -m gpu tests` on a fully installed machine).
  NAVI_GPU_ONLY=1 python -m pytest -q -p no:cacheprovider -rs -m gpu tests 2>&1 | tee "$out/gpu_tests.log"
  [ "${PIPESTATUS[0]}" = 0 ] || exit 1
  [ "$what" = all ] || exit 0
fi
scene=$(ls "$corpus"/*.gmdag | head -n 1)
for n in 4096 8192; do
  navi bench trace --gmdag "$scene" --agents $n --device cuda --json | tee -a "$out/bench_trace.jsonl"
done
navi bench env --corpus "$corpus" --actors 8192 --steps 100 --device cuda --json | tee -a "$out/bench_env.jsonl"
for core in mamba2 gru; do
  navi bench train --corpus "$corpus" --actors 8192 --temporal-core $core --device cuda --json \
    | tee -a "$out/bench_train.jsonl"
done
if [ -f artifacts/anchors/learner_ceiling.py ]; then
  sed "s/for layers in (2, 4)/for layers in (2,)/" artifacts/anchors/learner_ceiling.py > "$out/ceiling2.py"
  python "$out/ceiling2.py" 2>&1 | tee "$out/anchor_learner_ceiling.jsonl"
fi
