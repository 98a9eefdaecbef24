#!/usr/bin/env bash
# The whole test suite on a fresh machine: creates/reuses .venv, installs, lints, runs pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
. scripts/venv.sh
ruff check depth_fusion_ros test launch scripts
# Two pytest-xdist workers: most of a test's time is waiting on other processes (nodes over DDS,
# a graph's start, a fault's clean-up), so two workers on two cores take ~8 min, not ~13.8
# (docs/performance.md, "The test suite on two workers"). Each worker is on its own ROS domain
# (test/conftest.py). DEPTH_FUSION_TEST_WORKERS=0 runs every test in this one process.
python -m pytest test -q -n "${DEPTH_FUSION_TEST_WORKERS:-2}" "$@"
# After the suite (which ignores the user cache and compiles as CI does): the fusion kernels for
# later runs, built in a process of their own at the lowest CPU priority (fusion/aot_background.py),
# so a fusion node started after this is warm; nothing when they are built. DEPTH_FUSION_AOT=0 skips it.
if [ "${DEPTH_FUSION_TORCH:-cpu}" != cuda ] && [ "${DEPTH_FUSION_AOT:-1}" != 0 ]; then
  depth-fusion kernels --if-missing --background || true
fi
