"""Camera images from other processes come over UDP, not shared memory.

A process that publishes raw images larger than its Fast DDS shared-memory segment (0.5 MB by
default; a 640x480 rgb8 image is 0.9 MB) through shared memory fills the segment with image
fragments. The samples of its other topics that then find no room are lost and repaired only
at their writer's next heartbeat (3 s by default): its poses and camera_info stall 1.5-3 s at
a time while its images keep coming (docs/nodes.md, "Large raw images"). Every camera driver,
``ros2 bag play`` and user client with Fast DDS's defaults is such a process, and we cannot
change its settings.

The reader decides which of its locators a publisher sends to. A ``data_reader`` profile
named after the image topic, with a UDPv4 unicast locator and no address (every interface),
makes every publisher send the images over UDP, whatever its own settings, and leaves its
shared memory to its small messages; the node's other readers keep the shared memory.
rmw_fastrtps picks such a profile by the topic's fully resolved name, so the package profile
names the default image topics (raw and ``/compressed``) and a node whose image topic is
remapped or namespaced on its command line gets a copy of the profile naming its own
(:func:`profile_with_udp_readers`, written once per distinct content under the user's cache).
"""

from __future__ import annotations

import hashlib
import itertools
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from ...user_cache import user_cache

#: What a reader profile for one topic looks like (the package profile holds the defaults').
READER_TEMPLATE = """  <data_reader profile_name="{topic}">
    <unicastLocatorList>
      <locator>
        <udpv4/>
      </locator>
    </unicastLocatorList>
  </data_reader>
"""
_READER_NAME = re.compile(r'<data_reader\s+profile_name="([^"]+)"')


def expand(name: str, namespace: str) -> str:
    """``name`` as ROS 2 expands it in ``namespace`` (relative names join the namespace)."""
    if name.startswith('/'):
        return name
    return namespace.rstrip('/') + '/' + name


def ros_args(argv: Sequence[str]) -> list[str]:
    """The arguments between each ``--ros-args`` and the next ``--`` (or the end)."""
    out: list[str] = []
    inside = False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
        elif arg == '--':
            inside = False
        elif inside:
            out.append(arg)
    return out


def remap_rules(argv: Sequence[str]) -> list[tuple[str | None, str, str]]:
    """``(node or None, from, to)`` of every ``-r`` / ``--remap`` rule, in order."""
    args = ros_args(argv)
    rules = []
    for flag, value in itertools.pairwise(args):
        if flag not in ('-r', '--remap') or ':=' not in value:
            continue
        lhs, to = value.split(':=', 1)
        node, _, source = lhs.rpartition(':')
        rules.append((node or None, source, to))
    return rules


def resolved_topic(topic: str, node_name: str, argv: Sequence[str]) -> str:
    """The fully resolved name of ``topic`` for a node started with ``argv``.

    Follows ROS 2's rules for the command line: ``__node`` and ``__ns`` remaps first, then the
    first rule (global, or for this node) whose source expands to the same name. Rules from a
    parameter file are not seen (none of ours come from there); the result is then the
    default and only costs the images their UDP path.
    """
    rules = remap_rules(argv)
    namespace = '/'
    for node, source, to in rules:
        if source == '__node' and node in (None, node_name):
            node_name = to
    for node, source, to in rules:
        if source == '__ns' and node in (None, node_name):
            namespace = to if to.startswith('/') else '/' + to
    expanded = expand(topic, namespace)
    for node, source, to in rules:
        if source.startswith('__') or node not in (None, node_name):
            continue
        if expand(source, namespace) == expanded:
            return expand(to, namespace)
    return expanded


def reader_topics(profile_text: str) -> set[str]:
    """Topics a ``data_reader`` profile of the file is named after."""
    return set(_READER_NAME.findall(profile_text))


def derived_profile_dir() -> Path:
    """Where the copies naming other image topics are written (the user's cache)."""
    return user_cache('fastdds')


def profile_with_udp_readers(profile: Path, topics: Iterable[str], cache: Path | None = None) -> Path:
    """``profile``, or a copy of it that also names ``topics`` as UDP readers.

    The copy lives under ``cache`` (default :func:`derived_profile_dir`), named by its content,
    so every node with the same topics reuses one file.
    """
    text = profile.read_text()
    missing = [t for t in dict.fromkeys(topics) if t not in reader_topics(text)]
    if not missing:
        return profile
    extra = ''.join(READER_TEMPLATE.format(topic=t) for t in missing)
    head, tail = text.rsplit('</profiles>', 1)
    derived = head + extra + '</profiles>' + tail
    root = cache or derived_profile_dir()
    root.mkdir(parents=True, exist_ok=True)
    path = root / f'profile_{hashlib.sha1(derived.encode()).hexdigest()[:12]}.xml'
    if not path.is_file() or path.read_text() != derived:
        tmp = path.with_suffix(f'.{os.getpid()}.tmp')
        tmp.write_text(derived)
        tmp.replace(path)  # atomic: a node starting beside this one reads a whole file
    return path
