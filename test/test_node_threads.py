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
