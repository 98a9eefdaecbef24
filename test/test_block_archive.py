"""The disk archive of evicted map blocks: a bounded map that loses nothing (core, no ROS)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.mapping.block_archive import LOCK_NAME, PREFIX, BlockArchive, remove_stale
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.keyframe_store import KeyframeStore
from depth_fusion_ros.mapping.map_file import load_tsdf, save_tsdf
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF

pytestmark = pytest.mark.usefixtures('one_torch_thread')

CAMERA = PinholeCamera(160, 120, 131.25, 131.25, 79.5, 59.5)
WALL = np.full((CAMERA.height, CAMERA.width), 1.5, np.float32)
#: Along a 6 m wall and back: about 300 blocks against a cap of 100.
THERE_AND_BACK = [*np.linspace(0.0, 6.0, 13), *np.linspace(6.0, 0.0, 13)]


def _slide(config: MapConfig, xs=THERE_AND_BACK) -> TorchTSDF:
    tsdf = TorchTSDF(config)
    for x in xs:
        T = np.eye(4)
        T[0, 3] = x
        tsdf.integrate(WALL, T, CAMERA)
        assert tsdf.n_blocks <= config.max_blocks
    return tsdf


def _sorted_vertices(mesh) -> np.ndarray:
    v = mesh.vertices
    return v[np.lexsort(v.T[::-1])]


def _config(tmp_path, **kw) -> MapConfig:
    return MapConfig(engine='torch', voxel_size=0.04, archive_dir=str(tmp_path / 'archive'), **kw)


def test_a_bounded_map_with_its_archive_is_the_unbounded_map(tmp_path):
    """Evicted blocks come back bit for bit when the camera returns, so the bounded map, archive
    included, is exactly the map that never evicted; memory stays at the cap."""
    bounded = _slide(_config(tmp_path, max_blocks=100))
    unbounded = _slide(_config(tmp_path, max_blocks=100_000))
    assert bounded.evicted_blocks > 200 and bounded.archive.restored > 200 and bounded.lost_blocks == 0
    assert bounded.n_blocks == 100 and bounded.n_blocks + bounded.archived_blocks == unbounded.n_blocks
    assert bounded.memory_bytes <= 100 * bounded.config.bytes_per_block + 100 * 3 * 8
    np.testing.assert_array_equal(_sorted_vertices(bounded.mesh()), _sorted_vertices(unbounded.mesh()))
    folder = bounded.archive.path.parent
    assert folder.parent == tmp_path / 'archive' and folder.exists()
    bounded.close()
    assert not folder.exists()  # the spill area goes with the map


def test_a_full_archive_loses_blocks_and_says_so(tmp_path, caplog):
    bytes_per_block = 5 * 8**3 * 4
    config = _config(tmp_path, max_blocks=100, archive_max_mb=50 * bytes_per_block / 2**20)
    with caplog.at_level(logging.WARNING, logger='depth_fusion_ros.mapping.block_archive'):
        tsdf = _slide(config, THERE_AND_BACK[:13])
    assert tsdf.archived_blocks <= 50 and tsdf.lost_blocks > 0
    # every evicted block is archived now, was restored, or is counted lost
    assert tsdf.evicted_blocks == tsdf.lost_blocks + tsdf.archived_blocks + tsdf.archive.restored
    assert 'lost: the archive is full (50 blocks' in caplog.text


def test_a_disk_that_refuses_the_archive_loses_blocks_and_the_map_goes_on(tmp_path, caplog):
    blocker = tmp_path / 'not_a_directory'
    blocker.write_text('a file where the archive directory should be')
    config = MapConfig(engine='torch', voxel_size=0.04, max_blocks=100, archive_dir=str(blocker / 'sub'))
    with caplog.at_level(logging.WARNING, logger='depth_fusion_ros.mapping.block_archive'):
        tsdf = _slide(config, THERE_AND_BACK[:13])
    assert tsdf.archived_blocks == 0 and tsdf.lost_blocks == tsdf.evicted_blocks > 0
    assert 'writing' in caplog.text and 'failed' in caplog.text
    assert tsdf.n_blocks == 100 and not tsdf.mesh().is_empty


def test_put_take_and_read_round_trip(tmp_path):
    archive = BlockArchive(8, tmp_path)
    coords = torch.tensor([[0, 0, 0], [1, -2, 3], [-5, 4, 0]])
    tsdf, weight = torch.rand(3, 8), torch.rand(3, 8)
    colour = torch.rand(3, 3, 8) * 255
    assert archive.put(coords, tsdf, weight, colour) == 3 and archive.n_blocks == 3
    c = archive.coords()
    t, w, col = archive.read(c)
    order = [c.tolist().index(row) for row in coords.tolist()]
    torch.testing.assert_close(t[order], tsdf, rtol=0, atol=0)
    torch.testing.assert_close(col[order], colour, rtol=0, atol=0)
    found, t, w, col = archive.take(torch.tensor([[9, 9, 9], [-5, 4, 0], [1, -2, 3]]))
    assert found.tolist() == [False, True, True] and archive.n_blocks == 1
    torch.testing.assert_close(w, weight[[2, 1]], rtol=0, atol=0)
    torch.testing.assert_close(t, tsdf[[2, 1]], rtol=0, atol=0)
    # Freed slots are reused: the file does not grow.
    size = archive.disk_bytes
    archive.put(coords[1:], tsdf[1:], weight[1:], colour[1:])
    assert archive.disk_bytes == size and archive.n_blocks == 3
    archive.close()
    assert archive.n_blocks == 0 and archive.path is None


def test_a_map_file_larger_than_the_cap_loads_around_the_last_camera(tmp_path):
    """The map file holds the whole map (archive included) and where the camera last was; a node
    with a smaller cap holds the blocks nearest that position and archives the rest."""
    big = _slide(_config(tmp_path, max_blocks=100), THERE_AND_BACK[:13])  # ends at x = 6 m
    path = tmp_path / 'wall.tsdf'
    assert save_tsdf(big, path, 'map') == big.n_blocks + big.archived_blocks
    loaded = TorchTSDF(_config(tmp_path, max_blocks=100))
    assert load_tsdf(loaded, path) == 'map'
    assert loaded.n_blocks == 100 and loaded.archived_blocks == big.archived_blocks
    np.testing.assert_allclose(loaded.camera_position, [6.0, 0.0, 0.0])
    centres = (loaded.blocks().coords.double() + 0.5) * loaded.config.block_m
    assert centres[:, 0].min() > 3.0  # the blocks near the last camera are the ones in memory
    np.testing.assert_array_equal(_sorted_vertices(loaded.mesh()), _sorted_vertices(big.mesh()))
    with pytest.raises(ValueError, match=r'with map\.archive off'):
        load_tsdf(TorchTSDF(_config(tmp_path, max_blocks=100, archive=False)), path)


def _mapped_from(tensor: torch.Tensor, path) -> bool:
    """Whether the tensor's memory is a mapping of the file ``path`` (Linux: /proc/self/maps)."""
    address = tensor.data_ptr()
    for line in Path('/proc/self/maps').read_text().splitlines():
        fields = line.split()
        low, high = (int(x, 16) for x in fields[0].split('-'))
        if low <= address < high:
            return len(fields) > 5 and fields[5] == str(path)
    return False


def test_a_map_larger_than_memory_goes_through_its_file_a_part_at_a_time(tmp_path, monkeypatch):
    """Saving reads the archive back a chunk at a time and loading maps the file instead of
    reading it: at most CHUNK blocks pass through memory at once either way, and the map that
    comes back, its base included, is the one saved, bit for bit."""
    import depth_fusion_ros.mapping.map_file as map_file
    import depth_fusion_ros.mapping.torch_tsdf as torch_tsdf

    monkeypatch.setattr(map_file, 'CHUNK', 16)
    monkeypatch.setattr(torch_tsdf, 'LOAD_CHUNK', 16)
    big = _slide(_config(tmp_path, max_blocks=100), THERE_AND_BACK[:13])
    assert big.archived_blocks > 100
    coords, load = big.whole_map()
    asked: list[int] = []

    def spy(rows: torch.Tensor):
        asked.append(int(rows.numel()))
        return load(rows)

    monkeypatch.setattr(big, 'whole_map', lambda: (coords, spy))
    puts: list[int] = []
    path = tmp_path / 'wall.tsdf'
    store = KeyframeStore(max_bytes=2**20)
    store.add(1.0, WALL, np.eye(4), CAMERA)
    base = big.blocks().clone()
    assert map_file.save_tsdf(big, path, 'map', store=store, base=base) == coords.shape[0]
    assert max(asked) == 16 and sum(asked) == coords.shape[0]
    state = map_file.read_state(path)
    assert state['format'] == map_file.FORMAT
    assert _mapped_from(state['tsdf'], path)  # mapped, not read
    loaded = TorchTSDF(_config(tmp_path, max_blocks=100))
    original_put = loaded.archive.put
    monkeypatch.setattr(
        loaded.archive, 'put', lambda c, *a: puts.append(int(c.shape[0])) or original_put(c, *a)
    )
    result = map_file.load_map(loaded, path, KeyframeStore(max_bytes=2**20))
    assert max(puts) <= 16 and sum(puts) == big.archived_blocks
    np.testing.assert_array_equal(_sorted_vertices(loaded.mesh()), _sorted_vertices(big.mesh()))
    assert result.keyframes == 1 and _mapped_from(result.base.tsdf, path)
    torch.testing.assert_close(result.base.tsdf, base.tsdf, rtol=0, atol=0)
    torch.testing.assert_close(result.base.coords, base.coords, rtol=0, atol=0)
    # A truncated file is a one-line error, not a traceback or a map with holes.
    cut = tmp_path / 'cut.tsdf'
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ValueError, match='not readable as a map'):
        map_file.read_state(cut)


def test_a_format_1_map_file_still_loads(tmp_path):
    """Files written before the streamed layout (one torch.save of the whole map) load as they did."""
    from depth_fusion_ros.mapping.map_file import FORMAT_1

    big = _slide(_config(tmp_path, max_blocks=100_000), THERE_AND_BACK[:5])
    grid = big.blocks()
    path = tmp_path / 'old.tsdf'
    old = {'format': FORMAT_1, 'voxel_size': 0.04, 'block_size': 8, 'truncation': float(big.trunc)}
    old.update(world_frame='odom', coords=grid.coords, tsdf=grid.tsdf, weight=grid.weight, colour=grid.colour)
    torch.save(old, path)
    loaded = TorchTSDF(_config(tmp_path, max_blocks=100_000))
    assert load_tsdf(loaded, path) == 'odom' and loaded.n_blocks == big.n_blocks
    np.testing.assert_array_equal(_sorted_vertices(loaded.mesh()), _sorted_vertices(big.mesh()))


def test_a_negative_archive_cap_is_refused():
    with pytest.raises(ValueError, match=r'map\.archive_max_mb'):
        MapConfig(archive_max_mb=-1.0).validate()


def test_archives_left_by_killed_processes_are_removed_by_the_next_one(tmp_path):
    """A process killed before it could delete its archive leaves the directory, its lock free;
    the next archive made there removes it, and never one whose owner holds its lock (another
    process, even one in another PID namespace)."""
    import subprocess
    import sys

    holder = (
        'import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT); '
        'fcntl.flock(fd, fcntl.LOCK_EX); print("held", flush=True); time.sleep(60)'
    )
    dead, alive = tmp_path / f'{PREFIX}1_dead', tmp_path / f'{PREFIX}2_alive'
    for folder in (dead, alive):
        folder.mkdir()
        (folder / 'blocks.f32').write_bytes(b'\0' * 64)
        (folder / LOCK_NAME).touch()
    owner = subprocess.Popen(
        [sys.executable, '-c', holder, str(alive / LOCK_NAME)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert owner.stdout.readline().strip() == 'held'
        archive = BlockArchive(8, tmp_path)
        one = torch.zeros((1, 8))
        archive.put(torch.zeros((1, 3), dtype=torch.int64), one, one, torch.zeros(1, 3, 8))
        assert not dead.exists() and alive.exists()
        mine = archive.path.parent
        assert remove_stale(tmp_path) == 0 and mine.exists()  # its own lock is held too
        archive.close()
        assert not mine.exists()
    finally:
        owner.kill()
        owner.wait()
    assert remove_stale(tmp_path) == 1 and not alive.exists()  # its owner is gone now


def test_map_node_archives_under_ros_home_by_default(monkeypatch, tmp_path):
    """Not the temporary directory (memory on some systems): $ROS_HOME, ~/.ros by default."""
    from depth_fusion_ros.nodes.map_node import default_archive_dir

    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    assert default_archive_dir() == tmp_path / 'depth_fusion_ros' / 'map_archive'
    monkeypatch.delenv('ROS_HOME')
    assert default_archive_dir().parts[-3:] == ('.ros', 'depth_fusion_ros', 'map_archive')


def test_a_full_disk_loses_the_blocks_instead_of_killing_the_node(tmp_path, monkeypatch):
    """The file's space is allocated before the memory map writes into it: on a full disk the
    allocation fails with an OSError (counted), not a SIGBUS in the middle of a write."""
    import errno
    import os

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, 'No space left on device')

    monkeypatch.setattr(os, 'posix_fallocate', full, raising=False)
    archive = BlockArchive(8, tmp_path)
    one = torch.ones((2, 8))
    assert archive.put(torch.tensor([[0, 0, 0], [1, 0, 0]]), one, one, torch.ones((2, 3, 8))) == 0
    assert archive.lost == 2 and archive.n_blocks == 0
    monkeypatch.undo()
    assert archive.put(torch.tensor([[0, 0, 0]]), one[:1], one[:1], torch.ones((1, 3, 8))) == 1  # space again
    archive.close()


def test_ros_home_is_expanded_in_path_parameters(monkeypatch, tmp_path):
    from depth_fusion_ros.ros_home import expand_ros_home

    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    assert expand_ros_home('$ROS_HOME/a/b.pt') == tmp_path / 'a' / 'b.pt'
    assert expand_ros_home('${ROS_HOME}/b.pt') == tmp_path / 'b.pt'
    assert expand_ros_home('/x/$ROS_HOME/b.pt') == Path('/x/$ROS_HOME/b.pt')  # only a leading one
    assert expand_ros_home('$ROS_HOMEX/b.pt') == Path('$ROS_HOMEX/b.pt')
    monkeypatch.delenv('ROS_HOME')
    assert expand_ros_home('$ROS_HOME/b.pt') == Path.home() / '.ros' / 'b.pt'
    assert expand_ros_home('~/b.pt') == Path.home() / 'b.pt'
