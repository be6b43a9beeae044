# `navi bench learn` with the full protocol (3 seeds x mamba2 and gru, 600 s each) on a CUDA host
# without a package registry. Usage: bash tests/gpu_learn.sh OUT_DIR [GPUS] [extra bench learn options]
# With GPUS > 1 every GPU trains one run at a time; the split corpora are reused from
# artifacts/corpus/bench-learn (copy them there first; the pk3 is needed only to build them).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/gpu_env.sh"
out=${1:?usage: gpu_learn.sh OUT_DIR [GPUS]}
gpus=${2:-$(nvidia-smi -L | wc -l)}
shift $(( $# >= 2 ? 2 : 1 ))
export PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True NCCL_NVLS_ENABLE=0
navi bench learn --seeds 3 --temporal-core mamba2,gru --device cuda --gpus "$gpus" --parallel "$gpus" \
  --out "$out" "$@"
