"""The GIL switch interval of the graph's processes (nodes/gil.py)."""

from __future__ import annotations

import sys

import pytest

from depth_fusion_ros.nodes import gil


def test_default_and_environment_interval_and_a_bad_value_is_named(monkeypatch):
    monkeypatch.delenv(gil.ENV, raising=False)
    assert gil.configured_interval() == gil.SWITCH_INTERVAL_S
    monkeypatch.setenv(gil.ENV, '0.002')
    before = sys.getswitchinterval()
    try:
        assert gil.set_switch_interval() == before
        assert sys.getswitchinterval() == pytest.approx(0.002)
    finally:
        sys.setswitchinterval(before)
    for bad in ('0', '-1', 'fast'):
        monkeypatch.setenv(gil.ENV, bad)
        with pytest.raises(ValueError, match=gil.ENV):
            gil.configured_interval()
