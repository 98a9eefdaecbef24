"""The nodes' executors (nodes/node_executor.py): chosen by DEPTH_FUSION_EXECUTOR, spun to a stop."""

from __future__ import annotations

import threading
import time

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from depth_fusion_ros.nodes.node_executor import (  # noqa: E402
    ENV,
    executor_choice,
    make_node_executor,
    spin_until,
)
from depth_fusion_ros.nodes.testing import TEST_DOMAINS, pick_free_domain  # noqa: E402


@pytest.mark.parametrize('choice', ['events', 'single'])
def test_executors_in_a_private_context_deliver_and_stop_from_their_threads(choice):
    """What the composed graph does: two nodes of one private context, each on its own
    executor in its own thread, messages delivered between them, and both loops stopped by a
    flag within their wait (``EventsExecutor.spin()`` instead never returned)."""
    domain_id, lock = pick_free_domain(TEST_DOMAINS)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    received: list[str] = []
    try:
        talker, listener = Node('talker', context=context), Node('listener', context=context)
        listener.create_subscription(String, 'chatter', lambda m: received.append(m.data), 10)
        pub = talker.create_publisher(String, 'chatter', 10)
        talker.create_timer(0.02, lambda: pub.publish(String(data='hello')))
        threads = []
        for node in (talker, listener):
            executor, line = make_node_executor(choice, context)
            assert ('events' in line) == (choice == 'events'), line
            executor.add_node(node)
            thread = threading.Thread(
                target=spin_until, args=(executor, lambda: context.ok() and not stop.is_set()), daemon=True
            )
            thread.start()
            threads.append((executor, thread))
        deadline = time.monotonic() + 20.0
        while len(received) < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(received) >= 5 and set(received) == {'hello'}
        stop.set()
        for _, thread in threads:
            thread.join(5.0)
        assert not any(thread.is_alive() for _, thread in threads)
        for executor, _ in threads:
            executor.shutdown(timeout_sec=1.0)
        talker.destroy_node()
        listener.destroy_node()
    finally:
        stop.set()
        context.try_shutdown()
        if lock is not None:
            lock.close()


def test_executor_choice_reads_the_environment(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    assert executor_choice() == 'events'
    monkeypatch.setenv(ENV, ' Single ')
    assert executor_choice() == 'single'
    monkeypatch.setenv(ENV, 'evnets')
    with pytest.raises(ValueError, match="DEPTH_FUSION_EXECUTOR='evnets'"):
        executor_choice()


def test_run_rejects_a_bad_executor_choice_before_the_graph_starts(monkeypatch, capsys, tmp_path):
    """``depth-fusion run`` (composed or as processes) checks the variable first: one line, exit 1."""
    from depth_fusion_ros.cli.main import main

    monkeypatch.setenv(ENV, 'evnets')
    assert main(['run', '--bag', str(tmp_path / 'no_bag')]) == 1
    err = capsys.readouterr().err
    assert "DEPTH_FUSION_EXECUTOR='evnets'" in err and 'Traceback' not in err
