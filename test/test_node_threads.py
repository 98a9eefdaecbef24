"""A node process started on its own takes its share of the cores unless OMP_NUM_THREADS says."""

from __future__ import annotations

from depth_fusion_ros.nodes import threads


def test_a_node_takes_a_third_of_the_usable_cores_unless_omp_num_threads_is_set(monkeypatch):
    monkeypatch.setattr(threads, 'usable_cores', lambda: 2)
    assert threads.node_threads({}) == 1  # 2 cores, 3 node processes: one each, not two
    monkeypatch.setattr(threads, 'usable_cores', lambda: 16)
    assert threads.node_threads({}) == 5
    assert threads.node_threads({'OMP_NUM_THREADS': '3'}) is None  # torch follows it
    assert threads.usable_cores  # the real one: this process's affinity


def test_opencv_and_the_guard_queries_take_the_nodes_share(monkeypatch):
    """OpenCV's pool and the guard's k-d tree queries follow the node's torch threads."""
    import cv2
    import torch

    from depth_fusion_ros.fusion import neighbour_median

    before_torch, before_cv = torch.get_num_threads(), cv2.getNumThreads()
    monkeypatch.delenv('OMP_NUM_THREADS', raising=False)
    monkeypatch.setattr(threads, 'usable_cores', lambda: 2)
    try:
        line = threads.apply_node_threads()
        assert line.startswith('torch and OpenCV threads: 1')
        assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
        assert neighbour_median._query_workers() == 1
    finally:
        torch.set_num_threads(before_torch)
        cv2.setNumThreads(before_cv)
