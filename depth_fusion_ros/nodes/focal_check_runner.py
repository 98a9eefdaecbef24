"""``multi_view_node``'s focal length check, off the callback thread (``multiview/focal_check.py``).

Only the frames the check wants as its next sample are queued (:mod:`.check_runner`); once it
disagrees and ``focal_check.mode`` is correct, :meth:`FocalCheckRunner.camera_for` gives the
camera with the fitted focal length.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..camera import PinholeCamera
from ..multiview.focal_bias import focal_uncertainty
from ..multiview.focal_check import FOCAL_CHECK_MODES, FocalCheck, FocalCheckConfig, FocalEstimate
from .check_runner import PairedCheckRunner
from .params import ParamSpec, dataclass_specs

FOCAL_CHECK_LIMITS: dict[str, Any] = {
    'mode': FOCAL_CHECK_MODES,
    'min_baseline': (1e-4, None),
    'min_rotation_deg': (1e-3, 180.0),
    'pairs': (5, 10000),
    'lens_early_pairs': (0, 10000),
    'threshold': (1e-3, 0.9),
    'max_stderr': (1e-5, 1.0),
    'min_matches': (8, 100000),
    'features': (50, 100000),
}

FOCAL_CHECK_PARAMETERS: tuple[ParamSpec, ...] = tuple(
    dataclass_specs(FocalCheckConfig, 'focal_check', {}, FOCAL_CHECK_LIMITS)
)


class FocalCheckRunner(PairedCheckRunner):
    """Feeds a :class:`FocalCheck` from the callbacks on its own thread; reports the result once."""

    name = section = 'focal_check'
    check_type, config_type = FocalCheck, FocalCheckConfig

    def __init__(
        self, config: FocalCheckConfig, on_result: Callable[[PinholeCamera, FocalEstimate], None]
    ) -> None:
        super().__init__(config, on_result)
        #: ``(estimate, corrected camera)``: made once per estimate, not per frame.
        self._corrected: tuple[FocalEstimate, PinholeCamera] | None = None

    def camera_for(self, camera: PinholeCamera, after_lens: bool = False) -> PinholeCamera:
        """The camera the multi-view depth uses for frames of ``camera``: the fitted focal length
        once the check disagreed with this camera and ``focal_check.mode`` is correct, else
        ``camera`` itself. ``after_lens``: the images are undistorted with a lens the check
        fitted, and a disagreement is not taken (``FocalEstimate.applied``)."""
        result = self.result
        if result is None or not result.applied(self.config.mode, after_lens):
            return camera
        if camera != self.camera:
            return camera
        if self._corrected is None or self._corrected[0] is not result:
            self._corrected = (result, result.corrected(camera))
        return self._corrected[1]

    def uncertainty(self, prior: float, after_lens: bool = False) -> float:
        """How far the multi-view depth's focal length may still be off (relative,
        ``multiview/focal_bias.py``): ``prior`` until the check has read the stream (or what its
        early look bounded, when that agreed), then what it verified (``after_lens`` as for
        :meth:`camera_for`)."""
        result = self.result
        applied = result is not None and result.applied(self.config.mode, after_lens)
        check = self._check
        return focal_uncertainty(result, prior, applied, None if check is None else check.early)

    def status(self) -> str:
        """One phrase for the diagnostics."""
        if self.config.mode == 'off':
            return 'off'
        if self.result is not None:
            return f'{self.result.verdict}: fx {self.result.told_fx:.1f} -> {self.result.fx:.1f} px'
        return f'collecting ({self.collected} of {self.config.pairs} image pairs)'
