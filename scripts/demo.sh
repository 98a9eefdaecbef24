#!/usr/bin/env bash
# The main job on embedded defaults: creates/reuses .venv, installs, runs `depth-fusion demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
. scripts/venv.sh
depth-fusion demo "$@"
