"""The package builds the ROS way (colcon, ament_python) and its entry points resolve."""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ('depth-fusion', 'bag_replayer', 'single_view_node', 'multi_view_node', 'fusion_node', 'map_node')


def tracked_files() -> list[str]:
    out = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True, check=True)
    return [line for line in out.stdout.splitlines() if line]


def test_package_xml_is_valid_format_3():
    catkin_pkg = pytest.importorskip('catkin_pkg.package', reason='catkin_pkg comes with colcon')
    pkg = catkin_pkg.parse_package(ROOT / 'package.xml')
    pkg.validate()
    assert pkg.package_format == 3 and pkg.get_build_type() == 'ament_python'
    deps = {d.name for d in pkg.exec_depends}
    assert {'rclpy', 'sensor_msgs', 'geometry_msgs', 'std_msgs', 'builtin_interfaces'} <= deps


def test_every_ros_interface_package_the_code_imports_is_an_exec_depend():
    """rosdep installs what package.xml names: a message package imported but not declared
    works here (the pip wheels bring all of common_interfaces) and fails on a robot."""
    import re

    imported = set()
    for path in (ROOT / 'depth_fusion_ros').rglob('*.py'):
        imported |= set(re.findall(r'^\s*from (\w+_(?:msgs|srvs))\b', path.read_text(), flags=re.M))
    text = (ROOT / 'package.xml').read_text()
    declared = set(re.findall(r'<exec_depend>(\w+)</exec_depend>', text))
    assert imported and imported <= declared, sorted(imported - declared)


def test_console_scripts_resolve():
    from importlib.metadata import entry_points

    eps = {ep.name: ep for ep in entry_points(group='console_scripts') if ep.name in SCRIPTS}
    assert set(eps) == set(SCRIPTS)
    for ep in eps.values():
        module, _, attr = ep.value.partition(':')
        assert callable(getattr(importlib.import_module(module), attr))


def test_cli_help_lists_subcommands():
    out = subprocess.run(
        [sys.executable, '-m', 'depth_fusion_ros.cli.main', '--help'],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for sub in ('demo', 'synth', 'convert', 'evaluate', 'train', 'run', 'bench'):
        assert sub in out


def test_every_bench_module_imports_and_every_section_runs_by_name():
    """Each ``depth_fusion_ros/bench/*.py`` imports (sections share helpers: one that imported a
    helper since removed broke ``depth-fusion bench`` and no other test), and every name in
    ``SECTIONS`` has the ``TITLE`` and ``run`` the CLI calls."""
    from depth_fusion_ros import bench

    modules = sorted(p.stem for p in Path(bench.__file__).parent.glob('*.py') if p.stem != '__init__')
    loaded = {name: importlib.import_module(f'depth_fusion_ros.bench.{name}') for name in modules}
    for name in bench.SECTIONS:
        assert isinstance(loaded[name].TITLE, str) and callable(loaded[name].run)


@pytest.mark.skipif(
    shutil.which('colcon') is None, reason='colcon is not installed (pip install colcon-common-extensions)'
)
def test_colcon_build_and_test(tmp_path):
    """A ROS user's workflow: clone into a workspace, colcon build, colcon test."""
    src = tmp_path / 'src' / 'depth_fusion_ros'
    for rel in tracked_files():
        dst = src / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        if (ROOT / rel).is_file():
            shutil.copy2(ROOT / rel, dst)
    build = subprocess.run(
        ['colcon', 'build', '--event-handlers', 'console_direct-'],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    lib = tmp_path / 'install' / 'depth_fusion_ros' / 'lib' / 'depth_fusion_ros'
    for script in SCRIPTS:  # where `ros2 run depth_fusion_ros <script>` looks
        assert (lib / script).is_file(), f'{script} not installed to {lib}'
    share = tmp_path / 'install' / 'depth_fusion_ros' / 'share' / 'depth_fusion_ros'
    assert (share / 'package.xml').is_file()
    assert (share / 'config' / 'depth_fusion.yaml').is_file()
    assert (share / 'config' / 'cameras' / '7scenes_rgb.yaml').is_file()
    marker = (
        tmp_path / 'install' / 'depth_fusion_ros' / 'share' / 'ament_index' / 'resource_index' / 'packages'
    )
    assert (marker / 'depth_fusion_ros').is_file()
    # colcon test must find and run the package's tests (a tiny subset, to stay fast)
    test = subprocess.run(
        ['colcon', 'test', '--pytest-args', '-k', 'test_quaternion_round_trip'],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert test.returncode == 0, test.stdout + test.stderr
    result = subprocess.run(['colcon', 'test-result', '--all'], cwd=tmp_path, capture_output=True, text=True)
    assert 'Summary: 1 test, 0 errors, 0 failures' in result.stdout, result.stdout
