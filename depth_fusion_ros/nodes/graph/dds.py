"""Fast DDS profile and its shared-memory segments.

A best-effort 640x480 image does not fit the default 0.5 MB shared-memory segment, so most are
lost between processes. The runner points ``FASTRTPS_DEFAULT_PROFILES_FILE`` at the package's
``config/fastdds_shm.xml`` (10 MB segment) for itself and every child, unless the user already
set a profile. Nodes killed without shutdown leave their segments behind; these helpers find and
remove them.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import time
from collections.abc import MutableMapping, Sequence
from importlib import resources
from pathlib import Path

PROFILE_ENV = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def fastdds_profile_path() -> Path:
    """The package's Fast DDS profile (found in a checkout, a pip or a colcon install)."""
    path = Path(str(resources.files('depth_fusion_ros') / 'config' / 'fastdds_shm.xml'))
    if not path.is_file():
        raise FileNotFoundError(f'Fast DDS profile {path} is missing from the installed package')
    return path


def apply_fastdds_profile(env: MutableMapping[str, str] | None = None) -> str:
    """Point Fast DDS at the shared-memory profile in ``env`` (default ``os.environ``).

    Must happen before the first rclpy context of the process is initialised (Fast DDS reads
    the profile once). A profile the user already set is kept. Returns the profile in use.
    """
    env = os.environ if env is None else env
    for name in PROFILE_ENV:
        if env.get(name):
            return env[name]
    path = str(fastdds_profile_path())
    for name in PROFILE_ENV:
        env[name] = path
    return path


def profile_for_console_node(
    env: MutableMapping[str, str] | None = None, udp_readers: Sequence[str] = ()
) -> str:
    """What a node started on its own (console script, launch file) tells its user about Fast
    DDS, after applying the package's profile unless one is set (:func:`apply_fastdds_profile`).

    Without it, between processes a best-effort 640x480 image does not fit Fast DDS's default
    0.5 MB shared-memory segment: measured here, 12 of 60 images at 30 Hz arrived, against 60
    of 60 with the profile (reliable ones arrive either way). A camera driver publishes best
    effort, and ``input_qos: sensor_data`` then loses most frames silently. Must run before
    ``rclpy.init``. ``udp_readers``: the node's fully resolved camera image topics, read over
    UDP (:mod:`.dds_readers`; a copy of the profile names them when the package's does not).
    Returns the one line to log.
    """
    from .dds_readers import derived_profile_dir, profile_with_udp_readers, reader_topics

    env = os.environ if env is None else env
    if not any(env.get(name) for name in PROFILE_ENV):
        derived = str(profile_with_udp_readers(fastdds_profile_path(), udp_readers))
        for name in PROFILE_ENV:
            env[name] = derived
    path = apply_fastdds_profile(env)
    ours = path == str(fastdds_profile_path()) or Path(path).parent == derived_profile_dir()
    if not ours:
        return f'Fast DDS profile: {path} (yours, from the environment)'
    named = reader_topics(Path(path).read_text())
    over_udp = [t for t in udp_readers if t in named]
    readers = f'; camera images of {", ".join(over_udp)} read over UDP' if over_udp else ''
    return (
        f"Fast DDS profile: {path} (the package's: 10 MB shared-memory segments for images, "
        f'0.5 s discovery announcements{readers}; set FASTDDS_DEFAULT_PROFILES_FILE to use your own)'
    )


#: A participant's own segment (``fastrtps_<16 hex>``) and its lock file. Port segments
#: (``fastrtps_port<N>``) and their mutexes are shared by every participant on that port and
#: managed by Fast DDS itself, so they are never judged here.
PARTICIPANT_SEGMENT = re.compile(r'^fastrtps_[0-9a-f]{16}(_el)?$')


PORT_SEGMENT = re.compile(r'^(sem\.)?fastrtps_port\d+(_el|_mutex)?$')


def shm_segments(include_ports: bool = False) -> dict[str, float]:
    """Fast DDS participant segments (and port segments) in /dev/shm -> creation time."""
    root = Path('/dev/shm')
    if not root.is_dir():
        return {}
    out = {}
    for p in root.iterdir():
        if PARTICIPANT_SEGMENT.match(p.name) or (include_ports and PORT_SEGMENT.match(p.name)):
            with contextlib.suppress(OSError):
                out[p.name] = p.stat().st_ctime
    return out


def _shm_files_in(maps: Path) -> set[str]:
    """Names of the /dev/shm files one ``/proc/PID/maps`` lists (none once it is gone)."""
    names: set[str] = set()
    with contextlib.suppress(OSError):
        for line in maps.read_text().splitlines():
            idx = line.find('/dev/shm/')
            if idx >= 0:
                names.add(line[idx + len('/dev/shm/') :].split(' ')[0])
    return names


def mapped_shm_files() -> set[str]:
    """Names of /dev/shm files some live process has mapped (read from /proc/*/maps)."""
    mapped: set[str] = set()
    for maps in Path('/proc').glob('[0-9]*/maps'):
        mapped |= _shm_files_in(maps)
    return mapped


def participant_segments_of(pid: int) -> set[str]:
    """The participant segments one live process has mapped: what it leaves behind if killed."""
    return {n for n in _shm_files_in(Path(f'/proc/{pid}/maps')) if PARTICIPANT_SEGMENT.match(n)}


def owner_alive(segment: str) -> bool | None:
    """Whether the process that created a participant segment still runs: Fast DDS holds an
    exclusive ``flock`` on the segment's lock file (``<segment>_el``) for its owner's life, so
    a lock this process can take has no owner. ``None``: no lock file to ask.

    What a mapping cannot tell: every participant of a graph maps the others' segments (the
    data comes through them), and Fast DDS keeps a segment mapped until its process ends, so
    a killed node's segment stays mapped by the launcher's own listener and by the nodes."""
    try:
        fd = os.open(Path('/dev/shm') / f'{segment}_el', os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return None
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


#: A segment younger than this (s) is never judged: its owner may be taking its lock.
SETTLE_S = 0.2


def orphan_segments(since: float, include_ports: bool = False) -> list[str]:
    """Participant segments created after ``since`` (epoch s) whose owner is gone: what a node
    killed without shutdown leaves behind (:func:`owner_alive`; a segment without a lock file
    when nobody maps it).

    Lock files (``*_el``) are judged with their segment. With ``include_ports`` also the port
    segments and mutexes nobody maps (a killed node leaves those too; ``fastdds shm clean``
    would remove them).
    """
    mapped = mapped_shm_files()
    now = time.time()
    alive: dict[str, bool] = {}  # by segment: a segment and its lock file are judged once
    orphans = []
    for name, created in shm_segments(include_ports).items():
        if created < since - 1.0:
            continue
        base = name[: -len('_el')] if name.endswith('_el') else name
        if base not in alive:
            owner = owner_alive(base) if PARTICIPANT_SEGMENT.match(name) else None
            alive[base] = base in mapped if owner is None else owner
        if not alive[base] and now - created >= SETTLE_S:
            orphans.append(name)
    return sorted(orphans)


def remove_segments(names: Sequence[str]) -> None:
    for name in names:
        with contextlib.suppress(OSError):
            (Path('/dev/shm') / name).unlink()
