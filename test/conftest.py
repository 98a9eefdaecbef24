"""Shared fixtures: isolated ROS domain, the optional ../shared/data sequences."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('DEPTH_FUSION_SHARED_DATA', ROOT.parent / 'shared' / 'data'))

# Each pytest process that runs tests talks DDS on a domain of its own and only over loopback,
# so parallel runs (CI, a developer's second terminal) and the two pytest-xdist workers
# scripts/test.sh starts never hear each other's nodes. The domain is a free one of the suite's
# range, locked for this process's life as a RosHarness or a `depth-fusion run` locks its own
# (nodes/graph/isolation.py), so no harness in the other worker takes it either. A worker
# inherits the controller's ROS_DOMAIN_ID and so always picks; one process keeps a domain the
# caller set.
if 'ROS_DOMAIN_ID' not in os.environ or os.environ.get('PYTEST_XDIST_WORKER'):
    from depth_fusion_ros.nodes.graph.isolation import pick_free_domain
    from depth_fusion_ros.nodes.testing import TEST_DOMAINS

    _SUITE_DOMAIN, _SUITE_DOMAIN_LOCK = pick_free_domain(TEST_DOMAINS)
    os.environ['ROS_DOMAIN_ID'] = str(_SUITE_DOMAIN)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Fusion kernels a developer built ahead of time (depth-fusion kernels, in ~/.cache) would make
# this machine's run differ from CI's: the suite compiles as CI does, and test_fusion_aot.py
# builds its own in a private cache.
os.environ['DEPTH_FUSION_AOT'] = '0'
# What nodes keep across runs (the adapted weights, the map archive) goes under $ROS_HOME
# (ros_home.py): a private one per pytest process, so no test writes into the user's ~/.ros.
os.environ['ROS_HOME'] = tempfile.mkdtemp(prefix='depth_fusion_test_ros_home_')
atexit.register(shutil.rmtree, os.environ['ROS_HOME'], ignore_errors=True)


@pytest.fixture(scope='module')
def one_torch_thread():
    """One intra-op torch thread for a module's tests (``pytestmark = usefixtures(...)``): on a
    loaded shared machine, torch's pool waits on descheduled workers at every small op (tens of
    times slower with two threads); the results are identical."""
    torch = pytest.importorskip('torch')
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def save_torchscript_depth_model(module, folder: Path, stem: str) -> Path:
    """Script a stand-in depth network into ``folder/stem.pt`` with its metadata YAML (160x120
    input, metric depth): what a user bringing their own TorchScript model provides."""
    import torch

    from depth_fusion_ros.singleview.metadata import ModelMetadata, write_metadata_yaml

    path = folder / f'{stem}.pt'
    torch.jit.script(module).save(str(path))
    metadata = ModelMetadata(input_width=160, input_height=120, depth_max=100.0)
    write_metadata_yaml(metadata, folder / f'{stem}.yaml')
    return path


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


# --- Synthetic sequences (depth_fusion_ros.data.synthetic): exact depth and poses, no shared
# data needed. Session-scoped and shared between tests: treat them as read-only.

#: Config of the ``synthetic_sequence`` / ``synthetic_tum_dir`` fixtures (320x240, 24 frames).
SYNTHETIC_FIXTURE_CONFIG = dict(width=320, height=240, frames=24, seed=0)


@pytest.fixture(scope='session')
def synthetic_sequence():
    """In-memory ``Sequence``: 320x240, 24 frames at 30 Hz, high parallax (0.6-1.2 m sweep
    over the sequence, ~4 cm between consecutive frames), depth ground truth at 320x240."""
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(**SYNTHETIC_FIXTURE_CONFIG, parallax='high'))


@pytest.fixture(scope='session')
def synthetic_sequence_low_parallax():
    """Same room as ``synthetic_sequence`` (same seed) seen with low parallax: panning
    10-18 degrees with only a few cm of translation over the 24 frames."""
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(**SYNTHETIC_FIXTURE_CONFIG, parallax='low'))


@pytest.fixture(scope='session')
def synthetic_tum_dir(tmp_path_factory):
    """TUM folder (rgb/, depth/, *.txt, camera.yaml, SOURCE.md) of the same frames as
    ``synthetic_sequence``, written once per session."""
    from depth_fusion_ros.data.synthetic import SynthConfig, write_synthetic_sequence

    out = tmp_path_factory.mktemp('synthetic') / 'synth_s0_high'
    return write_synthetic_sequence(out, SynthConfig(**SYNTHETIC_FIXTURE_CONFIG, parallax='high'))


@pytest.fixture(scope='session')
def tiny_model(tmp_path_factory) -> str:
    """A compact network checkpoint at 64x48 input (as depth-fusion train writes one): the
    shipped network's code paths, adaptable (``adapt: auto`` is on), ~25x cheaper to train."""
    import torch

    from depth_fusion_ros.singleview.architectures import build_model
    from depth_fusion_ros.singleview.checkpoint import save_checkpoint
    from depth_fusion_ros.singleview.metadata import ModelMetadata

    torch.manual_seed(0)
    net = build_model('compact', {'input_width': 64, 'input_height': 48})
    path = tmp_path_factory.mktemp('tiny') / 'tiny_compact.pt'
    save_checkpoint(path, net, ModelMetadata(input_width=64, input_height=48))
    return str(path)


@pytest.fixture(scope='session')
def small_sequence():
    """A 160x120 synthetic room, 6 frames: multi-view at this size takes well under a second."""
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(width=160, height=120, frames=6, seed=3, parallax='high'))
