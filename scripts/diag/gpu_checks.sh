#!/usr/bin/env bash
# The GPU checks of issues 11, 13, 14 and 15 in one go, for a machine with CUDA torch:
#   OUT=out_dir bash scripts/diag/gpu_checks.sh
# Steps, most important first, each with its own time limit, inside one overall budget
# (GPU_CHECKS_BUDGET seconds, default 420; a step that would start past it is skipped and
# says so), so a slow step cannot take the others with it:
#   1. pytest test/test_cuda.py (CPU vs CUDA equivalence; skipped on CPU-only CI);
#   2. with ROS wheels in .whl/ (cp312 manylinux wheels of the ros-jazzy-* packages and rosbags,
#      downloaded with `pip download --no-deps`: docs/performance.md "GPU"), the composed node
#      graph on --device cuda over real DDS (`bench --only node_graph`), every frame a keyframe
#      (multi_view_node.keyframe_every=1) of the bench's 100-frame synthetic bag: once at the
#      recorded 30 Hz (real time: drops are reported) and once paced at 10x (saturating: the
#      highest keyframe rate the graph sustains);
#   3. `depth-fusion bench --only SECTION --device cuda` for the filter, the sweep, the fusion
#      and the TSDF.
# The ROS wheels go into a venv under /tmp that sees the machine's torch through a .pth file
# (pip --target would drop the wheels' data files: their C libraries). Logs end up in
# OUT/logs.tar.gz and a table of steps in OUT/summary.txt (the device tool returns 8 files).
# STEPS (below) names the steps and their order explicitly; unset, SECTIONS (unset:
# multi_view_filter multi_view fusion mapping; empty: none) picks the bench sections, in
# order, SECTION_LIMIT (default 75) their seconds each; CUDA_TESTS=0 skips step 1. PROFILES=1
# adds, last, where each keyframe's host time goes (scripts/diag/cuda_host_split.py: fusion,
# map, adaptation) and every adaptation update timed in the bench's order
# (scripts/diag/adapt_update_times.py), about 100 s together on an H200.
set -uo pipefail
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
LOGS=$(mktemp -d)
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
BUDGET=${GPU_CHECKS_BUDGET:-420}
WHEELS=${ROS_WHEELS:-.whl}
DEVICE=${DEVICE:-cuda}  # DEVICE=cpu tries the script itself on a machine without a GPU
start=$SECONDS

step() {  # step NAME LIMIT_S CMD...: run CMD with a time limit, log it, note rc and seconds
  local name=$1 limit=$2
  shift 2
  local left=$((BUDGET - (SECONDS - start)))
  if [ "$left" -lt 20 ]; then
    echo "$name: skipped, overall budget spent" | tee -a "$OUT/summary.txt"
    return 0
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  echo "== $name (limit ${limit} s)"
  local t0=$SECONDS
  timeout "$limit" "$@" >"$LOGS/$name.log" 2>&1
  local rc=$?
  echo "$name: rc=$rc in $((SECONDS - t0)) s" | tee -a "$OUT/summary.txt"
  grep -v -E "it/s\]|frame/s\]" "$LOGS/$name.log" | tail -n "${TAIL:-12}"
}

{ nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv,noheader || echo "no nvidia-smi"; } | tee "$OUT/summary.txt"
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')" | tee -a "$OUT/summary.txt"

ros_venv() {  # the ROS wheels in a venv that sees the machine's torch; prints its python
  local RV=/tmp/ros_venv
  if [ ! -x "$RV/bin/python" ]; then
    $PY -m venv --without-pip "$RV" \
      && $PY -m pip install -q --no-index --no-deps --no-compile --ignore-installed --prefix "$RV" "$WHEELS"/*.whl \
      && $PY -c 'import site; print(site.getsitepackages()[0])' >"$(ls -d "$RV"/lib/python3*)/site-packages/zz_machine.pth"
  fi
  echo "$RV/bin/python"
}

node_graph() {  # node_graph STEP_NAME [SCRIPT ARGS...]: the graph bench (or a script) in the ROS venv
  local name=${1:-node_graph}
  shift || true
  if [ ! -d "$WHEELS" ]; then
    echo "node graph: skipped, no ROS wheels in $WHEELS" | tee -a "$OUT/summary.txt"
    return 0
  fi
  local ROSPY
  ROSPY=$(ros_venv)
  export AMENT_PREFIX_PATH=/tmp/ros_venv
  $ROSPY -c "import rclpy, torch, rosbags; print('ROS venv: rclpy', rclpy.__file__, 'torch', torch.__version__)" | tee -a "$OUT/summary.txt"
  # Every frame a keyframe of the recorded 30 Hz (drops reported), then paced at 10x (flat out).
  if [ "$name" = node_graph ]; then
    TAIL=40 step node_graph "${NODE_GRAPH_LIMIT:-240}" env DEPTH_FUSION_BENCH_GRAPH_SET="${NODE_GRAPH_SET:-multi_view_node.keyframe_every=1}" \
      DEPTH_FUSION_BENCH_GRAPH_RUNS="${NODE_GRAPH_RUNS:-composed:realtime:1,composed:paced:10}" \
      $ROSPY -m depth_fusion_ros.cli.main bench --only node_graph --device "$DEVICE" --json "$LOGS/bench_node_graph.json"
  elif [ "$name" = graph_default ]; then  # every default (keyframe policy included)
    TAIL=40 step graph_default "${NODE_GRAPH_LIMIT:-240}" env -u DEPTH_FUSION_BENCH_GRAPH_SET \
      DEPTH_FUSION_BENCH_GRAPH_RUNS="${GRAPH_DEFAULT_RUNS:-composed:realtime:1,processes:realtime:1}" \
      $ROSPY -m depth_fusion_ros.cli.main bench --only node_graph --device "$DEVICE" --json "$LOGS/bench_graph_default.json"
  else
    TAIL=60 step "$name" "${NODE_GRAPH_LIMIT:-240}" "$ROSPY" "$@"
  fi
}

# STEPS, in order: cuda_tests, node_graph, graph_default (every default; GRAPH_DEFAULT_RUNS),
# sv_stall (scripts/diag/sv_stall.py: the single-view node's keyframes, composed), bench:SECTION, split:STAGES (cuda_host_split.py --only
# STAGES), adapt_times, graph_profile (scripts/diag/graph_profile.py: yappi over the composed graph,
# NODE_GRAPH_LIMIT seconds), fusion_profile (scripts/diag/profile_fusion.py: every keyframe of a 640x480
# synthetic room fused at the node's 2048-point cap, and a cProfile of the fusion's host functions).
# Unset: the order below (SECTIONS and PROFILES as described above).
default_steps() {
  [ "${CUDA_TESTS:-1}" != 0 ] && echo cuda_tests
  echo node_graph
  for section in ${SECTIONS-multi_view_filter multi_view fusion mapping}; do echo "bench:$section"; done
  [ "${PROFILES:-0}" = 1 ] && echo split:fusion,mapping,adaptation,multi_view adapt_times
  return 0
}
for item in ${STEPS:-$(default_steps)}; do
  case "$item" in
    cuda_tests)  # the tests' conftest imports rclpy: the ROS venv's python when the wheels are here
      if [ -d "$WHEELS" ]; then TEST_PY=$(ros_venv); export AMENT_PREFIX_PATH=/tmp/ros_venv; else TEST_PY=$PY; fi
      TAIL=8 step cuda_tests 150 "$TEST_PY" -m pytest test/test_cuda.py -q -p no:cacheprovider -rs ;;
    node_graph) node_graph ;;
    graph_default) node_graph graph_default ;;
    graph_profile)  # every thread of the composed graph under yappi, every frame a keyframe, paced x10
      DEPTH_FUSION_BENCH_GRAPH_SET="${NODE_GRAPH_SET:-multi_view_node.keyframe_every=1}" \
        DEPTH_FUSION_BENCH_GRAPH_RUNS=composed:paced:10 YAPPI_CLOCK=cpu YAPPI_ONLY=depth_fusion_ros/ \
        node_graph graph_profile scripts/diag/graph_profile.py "$DEVICE" ;;
    sv_stall) DEPTH_FUSION_BENCH_GRAPH_RUNS="${SV_STALL_RUNS:-composed:realtime:1}" node_graph sv_stall scripts/diag/sv_stall.py "$DEVICE" ;;
    bench:*)
      section=${item#bench:}
      TAIL=16 step "bench_$section" "${SECTION_LIMIT:-75}" $PY -m depth_fusion_ros.cli.main bench --only "$section" \
        --device "$DEVICE" --repeats 3 --json "$LOGS/bench_$section.json" ;;
    split:*)
      stages=${item#split:}
      TAIL=40 step "split_${stages//,/_}" 150 $PY scripts/diag/cuda_host_split.py --device "$DEVICE" --repeats 30 --only "$stages" ;;
    adapt_times) TAIL=25 step adapt_update_times 100 $PY scripts/diag/adapt_update_times.py --device "$DEVICE" ;;
    fusion_profile)  # each keyframe's fusion at the node's point cap, and its host functions
      $PY -m depth_fusion_ros.cli.main synth /tmp/fusion_profile_room --frames 40 --seed 0 --width 640 --height 480 >/dev/null 2>&1
      TAIL=75 step fusion_profile 120 $PY scripts/diag/profile_fusion.py evaluate /tmp/fusion_profile_room --frames 40 \
        --stride 1 --single-view simulated --methods fused_fast --set fusion.max_points=2048 --device "$DEVICE" \
        --no-figures --out /tmp/fusion_profile_out ;;
    *) echo "unknown step $item" | tee -a "$OUT/summary.txt" ;;
  esac
done
tar -czf "$OUT/logs.tar.gz" -C "$LOGS" .
echo "== summary"
cat "$OUT/summary.txt"
