#!/usr/bin/env bash
# The whole test suite on a fresh machine: creates/reuses .venv, installs, lints, runs pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
. scripts/venv.sh
ruff check depth_fusion_ros test launch scripts
python -m pytest test -q "$@"
# After the suite (which ignores the user cache and compiles as CI does): the fusion kernels for
# later runs, built in a process of their own at the lowest CPU priority (fusion/aot_background.py),
# so a fusion node started after this is warm; nothing when they are built. DEPTH_FUSION_AOT=0 skips it.
if [ "${DEPTH_FUSION_TORCH:-cpu}" != cuda ] && [ "${DEPTH_FUSION_AOT:-1}" != 0 ]; then
  depth-fusion kernels --if-missing --background || true
fi
