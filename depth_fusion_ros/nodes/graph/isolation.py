"""A private ROS domain for each run: its own free domain ID and localhost-only discovery.

Why: two ``depth-fusion run`` on one machine (or one run beside a live robot) on the same
domain hear each other's topics, and the nodes silently mix both streams (the second
recording then holds the first run's frames). By default a run therefore

* picks a **free domain ID** from :data:`PRIVATE_DOMAINS`. "Free" means both: no other
  ``depth-fusion`` run holds the domain's lock file (``fcntl.flock`` on
  ``$TMPDIR/depth_fusion_domains/domain_N.lock``, held for the run's whole life, so two runs
  started in the same instant never pick the same one), and no DDS participant of that domain
  lives on this machine (its well-known UDP ports, the discovery multicast port
  ``7400 + 250 N`` and the unicast ports ``7410 + 250 N + 2 p`` of participants ``p = 0..4``,
  can be bound: Fast DDS, Cyclone DDS and Connext hold them exclusively while a participant
  exists);
* sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (ROS 2 Jazzy; honoured by the pip wheels'
  ``rmw_fastrtps_cpp`` together with our Fast DDS profile: the participant no longer joins
  the discovery multicast group, it finds peers on 127.0.0.1 only).

Both go into ``os.environ`` for the life of the run (the runner's own rclpy context is
initialised inside it, and every node process copies it), and are restored afterwards.

``--domain-id N`` joins a live system on purpose: that domain, no lock, and the discovery
range the environment already has, unless ``localhost_only`` is asked for.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import random
import socket
import tempfile
from collections.abc import Iterable, MutableMapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

log = logging.getLogger(__name__)

DOMAIN_ENV = 'ROS_DOMAIN_ID'
RANGE_ENV = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
#: Domains a private run picks from. ROS 2 on Linux allows 0-101 and 215-232 without
#: clashing with the ephemeral port range (32768-60999) for participant ports; 0 is everyone's
#: default and the test suite uses 1-100, so runs take 101 and 215-232 (19 concurrent runs).
PRIVATE_DOMAINS: tuple[int, ...] = (101, *range(215, 233))
#: Largest domain ID the RTPS port mapping allows (7400 + 250 * 232 + participants < 65536).
MAX_DOMAIN_ID = 232
#: Participant indices whose unicast discovery port is probed.
PROBED_PARTICIPANTS = 5


def domain_ports(domain: int, participants: int = PROBED_PARTICIPANTS) -> list[int]:
    """The RTPS well-known ports (spec 9.6.1.1) a participant of ``domain`` binds on this host:
    discovery multicast ``PB + DG*d``, then metatraffic unicast ``PB + DG*d + d1 + PG*p``."""
    base = 7400 + 250 * domain
    return [base] + [base + 10 + 2 * p for p in range(participants)]


def port_in_use(port: int) -> bool:
    """Whether some process on this host holds UDP ``port`` (a bind without SO_REUSEADDR fails)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(('0.0.0.0', port))
        except OSError as exc:
            return exc.errno in (errno.EADDRINUSE, errno.EACCES)
    return False


def domain_in_use(domain: int) -> bool:
    """Whether a DDS participant of ``domain`` lives on this machine (its ports are bound)."""
    return any(port_in_use(p) for p in domain_ports(domain))


def lock_dir() -> Path:
    path = Path(tempfile.gettempdir()) / 'depth_fusion_domains'
    path.mkdir(parents=True, exist_ok=True)
    return path


def try_lock(domain: int) -> IO[str] | None:
    """The open, exclusively locked lock file of ``domain``, or ``None`` when another run holds it."""
    f = open(lock_dir() / f'domain_{domain}.lock', 'a+')  # noqa: SIM115 - held for the whole run
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        return None
    f.seek(0)
    f.truncate()
    f.write(f'{os.getpid()}\n')
    f.flush()
    return f


def pick_free_domain(candidates: Iterable[int] = PRIVATE_DOMAINS) -> tuple[int, IO[str]]:
    """A domain no other run holds and no participant on this host uses, with its held lock.

    Candidates are tried in random order so concurrent runs rarely contend for one lock.
    """
    order = list(candidates)
    random.SystemRandom().shuffle(order)
    for domain in order:
        lock = try_lock(domain)
        if lock is None:
            continue
        if domain_in_use(domain):
            lock.close()
            continue
        return domain, lock
    raise RuntimeError(
        f'no free ROS domain among {len(order)} candidates ({min(order)}-{max(order)}): '
        'every one is held by another run or used on this machine; pass --domain-id N'
    )


@dataclass
class Isolation:
    """The domain a run uses, and how to undo what choosing it changed."""

    domain: int
    localhost_only: bool
    private: bool
    _lock: IO[str] | None = None
    _saved: dict[str, str | None] = field(default_factory=dict)
    _env: MutableMapping[str, str] | None = None

    def describe(self) -> str:
        scope = 'localhost-only discovery' if self.localhost_only else 'discovery on every network interface'
        if self.private:
            return (
                f'ROS domain {self.domain} (a free one, {scope}): no other ROS 2 graph hears this run; '
                'pass --domain-id N to join a live system'
            )
        return f'ROS domain {self.domain} (--domain-id, {scope}): this run joins whatever runs there'

    def close(self) -> None:
        """Restore the environment and release the domain's lock (idempotent)."""
        env = self._env
        if env is not None:
            for name, value in self._saved.items():
                if value is None:
                    env.pop(name, None)
                else:
                    env[name] = value
            self._env = None
        if self._lock is not None:
            with contextlib.suppress(OSError):
                self._lock.close()
            self._lock = None

    def __enter__(self) -> Isolation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_domain_id(domain: int) -> int:
    if not 0 <= int(domain) <= MAX_DOMAIN_ID:
        raise ValueError(f'--domain-id must be between 0 and {MAX_DOMAIN_ID}, got {domain}')
    return int(domain)


def isolate(
    domain_id: int | None = None,
    localhost_only: bool | None = None,
    env: MutableMapping[str, str] | None = None,
) -> Isolation:
    """Choose the run's domain and discovery range and put them in ``env`` (``os.environ``).

    ``domain_id=None``: a free private domain, localhost-only unless ``localhost_only=False``.
    A given ``domain_id``: that domain, and localhost-only only when ``localhost_only=True``
    (otherwise the environment's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` stays as it is).
    Call :meth:`Isolation.close` (or use it as a context manager) when the run ends.
    """
    env = os.environ if env is None else env
    lock = None
    if domain_id is None:
        domain, lock = pick_free_domain()
        private = True
        local = localhost_only is not False
    else:
        domain = check_domain_id(domain_id)
        private = False
        local = bool(localhost_only)
    iso = Isolation(domain, local or env.get(RANGE_ENV, '').upper() == 'LOCALHOST', private, lock)
    iso._env = env
    iso._saved = {DOMAIN_ENV: env.get(DOMAIN_ENV), RANGE_ENV: env.get(RANGE_ENV)}
    env[DOMAIN_ENV] = str(domain)
    if local:
        env[RANGE_ENV] = 'LOCALHOST'
    elif private:  # asked for a private domain reachable from other hosts
        env[RANGE_ENV] = 'SUBNET'
    log.info('%s', iso.describe())
    return iso
