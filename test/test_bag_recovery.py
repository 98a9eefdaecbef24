"""A truncated bag (a recorder that crashed) plays up to its last readable message, with one
warning, and ``depth-fusion convert --repair`` writes it into a clean bag."""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.rosbag2 import Reader
from run_bags import small_bag

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.data.bag_recovery import RecoveredBag, open_rosbag2
from depth_fusion_ros.data.rosbag_read import iter_messages


@pytest.fixture(scope='module', params=['mcap', 'sqlite3'])
def whole_bag(request, synthetic_tum_dir, tmp_path_factory) -> Path:
    return small_bag(synthetic_tum_dir, tmp_path_factory.mktemp(request.param) / 'whole', 24, request.param)


def truncated(bag: Path, dest: Path, keep: float = 0.5, metadata: bool = True) -> Path:
    """A copy of ``bag`` whose storage file is cut to ``keep`` of its size (as a crash leaves it)."""
    shutil.copytree(bag, dest)
    storage = next(p for p in dest.iterdir() if p.suffix in ('.mcap', '.db3'))
    os.truncate(storage, int(storage.stat().st_size * keep))
    if not metadata:
        (dest / 'metadata.yaml').unlink()
    return dest


def test_whole_bag_is_read_by_rosbags(whole_bag):
    reader = open_rosbag2(whole_bag)
    try:
        assert isinstance(reader, Reader) and reader.message_count == 96
    finally:
        reader.close()


@pytest.mark.parametrize('metadata', [True, False], ids=['metadata', 'no_metadata'])
def test_truncated_bag_reads_its_readable_part_with_one_warning(whole_bag, tmp_path, caplog, metadata):
    with pytest.raises(Exception, match=r'magic|malformed|metadata'):
        Reader(truncated(whole_bag, tmp_path / 'probe')).open()  # what rosbags says
    bag = truncated(whole_bag, tmp_path / 'cut', metadata=metadata)
    with caplog.at_level(logging.WARNING):
        reader = open_rosbag2(bag)
        assert isinstance(reader, RecoveredBag)
        n = reader.message_count
        got = list(reader.messages(reader.connections))
        reader.close()
        assert 20 <= n < 96 and len(got) == n
        total = '~96' if metadata else 'an unknown number of'
        assert f'recovered {n} of {total} messages from {bag}' in caplog.text
        # evaluate/run's reader: the same messages, decoded, and no second warning
        images = [m for t, _, m in iter_messages(bag, ['/camera/rgb/image_color'])]
    assert 5 <= len(images) < 24 and images[0].height == 240
    assert caplog.text.count('recovered ') == 1
    first = [(c.topic, t, bytes(raw)) for c, t, raw in got[:5]]
    with Reader(whole_bag) as whole:
        original = [(c.topic, t, bytes(raw)) for c, t, raw in whole.messages()]
    assert all(m in original for m in first)  # the same bytes as the whole bag


def test_replayer_plays_a_truncated_bag_up_to_its_end(whole_bag, tmp_path):
    pytest.importorskip('rclpy')
    bag = truncated(whole_bag, tmp_path / 'cut')
    with RecoveredBag(bag) as rec:
        n = rec.message_count
    proc = subprocess.run(
        [sys.executable, '-m', 'depth_fusion_ros.nodes.bag_replayer', '--ros-args', '-p', f'bag:={bag}',
         '-p', 'rate:=10.0', '-p', 'linger:=0.0'],
        capture_output=True, text=True, timeout=120, env=os.environ.copy(),
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert f'recovered {n} of ~96 messages' in out
    assert re.search(rf'playback ended: {n} messages in 1 pass', out), out


def test_convert_repair_writes_a_clean_bag(whole_bag, tmp_path, capsys):
    bag = truncated(whole_bag, tmp_path / 'cut', keep=0.6, metadata=False)
    out = tmp_path / 'repaired'
    assert main(['convert', '--repair', str(bag), str(out)]) == 0
    line = capsys.readouterr().out
    n = int(re.search(r'recovered (\d+) of an unknown number of messages', line).group(1))
    assert f'wrote {n} messages to {out}' in line
    with Reader(out) as reader:  # a whole bag again: rosbags opens it, metadata and all
        assert reader.message_count == n
        assert {c.topic for c in reader.connections} >= {'/camera/rgb/image_color', '/camera/pose'}


def test_unrecoverable_bag_is_one_line(tmp_path, capsys):
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'x.mcap').write_bytes(b'not an mcap at all')
    assert main(['convert', '--repair', str(tmp_path / 'junk'), str(tmp_path / 'out')]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith('depth-fusion convert: error:') and '\n' not in err
