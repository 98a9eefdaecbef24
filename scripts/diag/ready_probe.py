"""When a node says ready, and when a listener hears it (diagnostic for time to ready, issue 13).

    python scripts/diag/ready_probe.py single_view_node multi_view_node fusion_node
    FASTRTPS_DEFAULT_PROFILES_FILE=other.xml python scripts/diag/ready_probe.py ...

Starts a subscriber to ``depth_fusion/ready`` (on a free private domain, with the package's
Fast DDS profile unless one is set), waits ``PRE`` seconds (default 1), spawns the named node
modules and prints, per node, the time of its own ``ready`` log line and the arrival of its
ready line at the subscriber, both in seconds from the spawn. The gap is DDS discovery.
"""

import os
import re
import subprocess
import sys
import threading
import time

import rclpy
from rclpy.executors import MultiThreadedExecutor
from std_msgs.msg import String

from depth_fusion_ros.nodes.graph.dds import apply_fastdds_profile
from depth_fusion_ros.nodes.graph.isolation import isolate
from depth_fusion_ros.nodes.graph_events import TOPIC_READY, ready_qos

apply_fastdds_profile()
iso = isolate(None, None)
ctx = rclpy.context.Context()
rclpy.init(context=ctx)
node = rclpy.create_node('probe', context=ctx)
arr = {}
t0 = time.time()


def cb(msg):
    import json

    n = json.loads(msg.data)['node']
    arr.setdefault(n, time.time() - t0)


node.create_subscription(String, TOPIC_READY, cb, ready_qos(depth=20))
ex = MultiThreadedExecutor(context=ctx)
ex.add_node(node)
threading.Thread(target=ex.spin, daemon=True).start()
time.sleep(float(os.environ.get('PRE', '1.0')))
names = sys.argv[1:]
env = dict(os.environ, PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
procs = {}
ts = time.time()
for n in names:
    procs[n] = subprocess.Popen(
        [sys.executable, '-m', f'depth_fusion_ros.nodes.{n}'],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
logt = {}


def reader(n, p):
    for line in p.stdout:
        m = re.search(r'\[(\d+\.\d+)\] \[(\w+)\]: ready', line)
        if m:
            logt[n] = float(m.group(1)) - ts


threads = [threading.Thread(target=reader, args=(n, p), daemon=True) for n, p in procs.items()]
for t in threads:
    t.start()
time.sleep(8)
for n in names:
    print(
        n,
        f'log ready {logt.get(n, -1):.2f}',
        f'arrival {arr.get("/" + n, -1 + t0 - ts) - (ts - t0):.2f}',
    )
for p in procs.values():
    p.terminate()
