"""Shared fixtures: isolated ROS domain, the optional ../shared/data sequences."""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('DEPTH_FUSION_SHARED_DATA', ROOT.parent / 'shared' / 'data'))

# Each test session talks DDS on its own domain and only over loopback, so parallel runs
# (CI, a developer's second terminal) never hear each other's nodes.
os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(1, 100)))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def shared_sequence(name: str) -> Path:
    """Path of a sequence in ../shared/data, or skip the test saying why."""
    path = SHARED_DATA / name
    if not (path / 'rgb.txt').is_file():
        pytest.skip(f'shared dataset {name} not found at {path} (../shared/data is absent)')
    return path


@pytest.fixture
def tum_fr1_xyz() -> Path:
    return shared_sequence('tum_fr1_xyz_37')


@pytest.fixture
def redkitchen() -> Path:
    return shared_sequence('7scenes_redkitchen_000_499')
