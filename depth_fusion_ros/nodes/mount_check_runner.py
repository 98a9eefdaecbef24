"""``multi_view_node``'s mount check, off the callback thread (``multiview/mount_check.py``).

Only the frames the check wants as its next sample are queued (:mod:`.check_runner`); once it
disagrees and ``mount_check.mode`` is correct, :attr:`MountCheckRunner.rotation` is the turn
the node applies to every camera pose it reads from then on (``T_wc @ rotation``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..multiview.mount_check import MOUNT_CHECK_MODES, MountCheck, MountCheckConfig
from .check_runner import PairedCheckRunner
from .params import ParamSpec, dataclass_specs

MOUNT_CHECK_LIMITS: dict[str, Any] = {
    'mode': MOUNT_CHECK_MODES,
    'min_baseline': (1e-4, None),
    'min_rotation_deg': (1e-3, 180.0),
    'pairs': (5, 10000),
    'early_pairs': (0, 10000),
    'threshold_deg': (1e-3, 44.0),
    'max_stderr_deg': (1e-4, 45.0),
    'min_cost_rise': (0.0, 1.0),
    'max_patch_residual': (0.0, 100.0),
    'min_matches': (8, 100000),
    'features': (50, 100000),
}

MOUNT_CHECK_PARAMETERS: tuple[ParamSpec, ...] = tuple(
    dataclass_specs(MountCheckConfig, 'mount_check', {}, MOUNT_CHECK_LIMITS)
)

_IDENTITY = np.eye(4)
_IDENTITY.setflags(write=False)


class MountCheckRunner(PairedCheckRunner):
    """Feeds a :class:`MountCheck` from the callbacks on its own thread; reports the result once."""

    name = section = 'mount_check'
    check_type, config_type = MountCheck, MountCheckConfig

    @property
    def rotation(self) -> np.ndarray:
        """The turn (4x4) of the camera poses the check read (``T_wc @ rotation``): the fitted
        one once the check disagreed and ``mount_check.mode`` is correct, else the identity."""
        result = self.result
        if self.config.mode != 'correct' or result is None:
            return _IDENTITY
        return result.rotation()  # the identity unless it disagrees

    def status(self) -> str:
        """One phrase for the diagnostics."""
        if self.config.mode == 'off':
            return 'off'
        r = self.result
        if r is not None:
            turn = ', '.join(f'{v:+.2f}' for v in r.rotvec_deg)
            return f'{r.verdict}: turned [{turn}] deg ({r.observed} of 3 directions observed)'
        return f'collecting ({self.collected} of {self.config.pairs} image pairs)'
