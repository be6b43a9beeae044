#!/usr/bin/env bash
# Data-parallel PPO (DD-PPO) on several GPUs of one host over NCCL, for a CUDA host without a package
# registry (a 2-GPU benchmark host): builds the extensions in place (tests/gpu_env.sh), then runs
# `navi bench train --nproc N` at 8,192 actors per GPU: the one-process measurement (`--nproc 1`, the
# "single" field) first, then N ranks through torchrun, in one job; prints the JSON (per-rank and total
# SPS of env only / env + inference / env + training, scaling efficiency SPS(N) / (N x SPS(1))).
#   tests/gpu_dist.sh [CORPUS_DIR] [NPROC]      # default artifacts/bench-corpus, 2
#   CORES="mamba2 gru" tests/gpu_dist.sh ...    # temporal cores to measure (default mamba2)
#   tests/gpu_dist.sh CORPUS 4 --rank-scenes share # further arguments go to `navi bench train`
# A missing corpus is built first (procedural, 8 scenes at 512^3; every rank flies all 8 unless
# --rank-scenes share gives each a share).
set -euo pipefail
cd "$(dirname "$0")/.."
corpus=${1:-artifacts/bench-corpus}; nproc=${2:-2}; cores=${CORES:-mamba2}; shift $(( $# < 2 ? $# : 2 ))
out=${OUT:-artifacts/gpu-dist}; mkdir -p "$out"
source tests/gpu_env.sh
export NCCL_NVLS_ENABLE=0  # NVLink multicast (NVLS) stays off: on shared multi-GPU hosts it can take the GPUs out of service
export NAVI_DIST_TIMEOUT_S=${NAVI_DIST_TIMEOUT_S:-300}  # the first update includes torch.compile
nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv,noheader
python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'nccl', \
torch.cuda.nccl.version(), 'gpus', torch.cuda.device_count())"
if [ ! -f "$corpus/manifest.json" ]; then
  navi corpus build --default --out "$corpus" --count 8 --resolution 512 --device cuda
fi
for core in $cores; do
  navi bench train --corpus "$corpus" --actors 8192 --temporal-core "$core" --device cuda --nproc "$nproc" \
    --json "$@" | tee -a "$out/bench_train_nproc.jsonl"
done
