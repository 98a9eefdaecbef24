#!/usr/bin/env bash
# The GPU checks of issues 11, 13, 14 and 15 in one go, for a machine with CUDA torch and
# no ROS (the kernel benches and the CUDA tests import no ROS package):
#   OUT=out_dir bash scripts/diag/gpu_checks.sh
# Writes OUT/cuda_tests.log, OUT/bench_*.log and OUT/bench_*.json. Each step has its own time
# limit so a slow one cannot take the others with it.
set -uo pipefail
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0))"
timeout 110 $PY -m pytest test/test_cuda.py -q -p no:cacheprovider -rs 2>&1 | tee "$OUT/cuda_tests.log"
for section in fusion multi_view multi_view_filter mapping single_view adaptation; do
  echo "== bench $section"
  timeout 70 $PY -m depth_fusion_ros.cli.main bench --only "$section" --device cuda --repeats 3 \
    --json "$OUT/bench_$section.json" 2>&1 | grep -v "it/s\]" | tee "$OUT/bench_$section.log"
done
