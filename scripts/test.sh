#!/usr/bin/env bash
# The whole test suite on a fresh machine: creates/reuses .venv, installs, lints, runs pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
. scripts/venv.sh
ruff check depth_fusion_ros test launch scripts
python -m pytest test -q "$@"
