#!/usr/bin/env bash
# Create or reuse ./.venv and install everything depth_fusion_ros needs, from the package index.
# Sourced by scripts/demo.sh and scripts/test.sh; safe to run again (skips pip when nothing changed).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${DEPTH_FUSION_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"
# DEPTH_FUSION_TORCH=cuda: the CUDA build of the same torch (PyPI's torch==2.13.0 for Linux x86_64,
# CUDA 13; several GB) instead of the CPU build CI uses. scripts/demo.sh --cuda sets it.
TORCH_BUILD="${DEPTH_FUSION_TORCH:-cpu}"
case "$TORCH_BUILD" in
  cpu|cuda) ;;
  *) echo "scripts/venv.sh: DEPTH_FUSION_TORCH must be cpu or cuda, got '$TORCH_BUILD'" >&2; exit 2 ;;
esac

# Every dependency pinned to the versions the project is tested with (a fresh clone installs
# exactly what CI ran). Unpinned ros-* names resolve to newer distributions; a bare `torch` pulls GBs of CUDA.
REQUIREMENTS=(
  "ros-jazzy-rclpy==7.1.6"
  "ros-jazzy-common-interfaces==5.3.6"
  "ros-jazzy-rmw-fastrtps-cpp==8.4.3"
  "torch==2.13.0"
  "onnxruntime==1.32.0"
  "onnx==1.23.2"
  "onnxscript==0.7.2"
  "numpy==2.4.6"
  "opencv-python-headless==5.0.0.93"
  "scipy==1.17.1"
  "rosbags==0.11.9"
  "pyyaml==6.0.3"
  "tqdm==4.70.1"
  "matplotlib==3.11.2"
  "pytest==9.2.0"
  "pytest-xdist==3.8.0"
  "execnet==2.1.2"
  "ruff==0.17.6"
  "colcon-common-extensions==0.3.0"
)

if [ ! -x "$VENV/bin/python" ]; then
  echo "[venv] creating $VENV"
  "$PY" -m venv "$VENV"
fi
# shellcheck disable=SC1091
. "$VENV/bin/activate"

stamp="$VENV/.depth_fusion_stamp"
want="$(printf '%s\n' "torch build: $TORCH_BUILD" "${REQUIREMENTS[@]}" | cat - "$ROOT/setup.py" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[venv] installing dependencies (first run takes a minute or two)"
  if [ "$TORCH_BUILD" = cuda ]; then
    # --isolated: PyPI's wheel, not a CPU wheel a local pip configuration may point at.
    python -m pip install -q --disable-pip-version-check --isolated --force-reinstall "torch==2.13.0"
    python -c 'import sys, torch; sys.exit(0 if torch.version.cuda else "scripts/venv.sh: the installed torch " + torch.__version__ + " has no CUDA; install a CUDA build of torch==2.13.0 into .venv by hand")'
  else
    python -m pip install -q --disable-pip-version-check "torch==2.13.0"
  fi
  python -m pip install -q --disable-pip-version-check "${REQUIREMENTS[@]}"
  python -m pip install -q --disable-pip-version-check --no-deps -e "$ROOT"
  echo "$want" > "$stamp"
fi
# The package's bytecode, compiled once here rather than by every process that imports it: an
# editable install is not compiled by pip, and with PYTHONDONTWRITEBYTECODE (set on many CI and
# container images) Python never writes it, so each node process would compile ~200 modules
# at start, ~0.3 s of CPU, three times over on a graph's start (docs/performance.md, "Time to
# ready"). Up-to-date files are skipped; a stale .pyc is ignored by Python, not trusted.
python -m compileall -q -j 0 "$ROOT/depth_fusion_ros" > /dev/null
# ament_index look-ups (ros2 run style) resolve against the venv prefix.
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
