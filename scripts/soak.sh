#!/usr/bin/env bash
# Memory soak of the node graph, outside the normal suite: loops the benchmark bag through the
# graph as processes for DEPTH_FUSION_SOAK_SECONDS (default 1800 = 30 min) and prints the
# resident memory after warm-up and at the end, and the growth in % (target: within 5 %).
#   scripts/soak.sh                                   # 30 min, synthetic 640x480 room
#   DEPTH_FUSION_SOAK_SECONDS=300 scripts/soak.sh --sequence /path/to/tum_folder
# Uses ./.venv when it exists (scripts/venv.sh creates it); runs from the repository root.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
if [ -x "$ROOT/.venv/bin/python" ] && [ -z "${VIRTUAL_ENV:-}" ]; then
  # shellcheck disable=SC1091
  . "$ROOT/.venv/bin/activate"
fi
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
exec python -m depth_fusion_ros.cli.main bench --only soak "$@"
