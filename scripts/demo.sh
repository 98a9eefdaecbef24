#!/usr/bin/env bash
# The main job on embedded defaults: creates/reuses .venv, installs, runs `depth-fusion demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
# --cuda: install the CUDA build of torch into .venv (DEPTH_FUSION_TORCH=cuda) and run on the GPU.
args=()
for a in "$@"; do
  if [ "$a" = --cuda ]; then export DEPTH_FUSION_TORCH=cuda; args+=(--device cuda); else args+=("$a"); fi
done
# shellcheck disable=SC1091
. scripts/venv.sh
if [ "${DEPTH_FUSION_TORCH:-cpu}" = cuda ] && ! python -c 'import sys, torch; sys.exit(not torch.cuda.is_available())'; then
  echo "scripts/demo.sh: --cuda: torch $(python -c 'import torch; print(torch.__version__)') sees no CUDA device (driver missing or too old for CUDA 13?)" >&2
  exit 1
fi
# The fusion kernels built ahead of time (CPU), once: every later fusion node is warm at start.
if [ "${DEPTH_FUSION_TORCH:-cpu}" != cuda ]; then
  depth-fusion kernels --if-missing || echo "scripts/demo.sh: the fusion kernels could not be built ahead of time (see above); fusion nodes compile at start instead" >&2
fi
depth-fusion demo "${args[@]}"
