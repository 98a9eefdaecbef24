"""``evaluate``: how a calibration check runs on a loaded sequence (the time offset check, the
focal length check), before any method: its config from ``--set STAGE.*``, nothing when off,
one line when the sequence is too short to finish it, its verdict logged (a warning when it
disagrees). What each does with a disagreement is its own module's (``time_offset.py``,
``focal.py``)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from ..data.sequence import Sequence
from ..multiview.params import apply_overrides

log = logging.getLogger(__name__)


def check_config(params: dict, stage: str, default: Any) -> Any:
    """A check's config: ``default`` with the ``--set STAGE.*`` overrides of ``params``."""
    return apply_overrides(default, params.get(stage, {}), stage)


def run_check(
    sequence: Sequence, params: dict, stage: str, default: Any, run: Callable[[Sequence, Any], Any], what: str
) -> tuple[Any, Any]:
    """``(config, estimate)``: the check's config and its estimate, ``None`` when it is off or
    ran out of frames. ``run(sequence, config)`` returns the check fed with the sequence."""
    config = check_config(params, stage, default)
    if config.mode == 'off':
        return config, None
    check = run(sequence, config)
    estimate = check.result
    if estimate is None:
        pairs = check.pairs if isinstance(check.pairs, int) else len(check.pairs)
        log.info(
            '%s: %s not checked: %d image pairs in %d frames, %d needed',
            sequence.name,
            what,
            pairs,
            len(sequence.frames),
            config.pairs,
        )
        return config, None
    level = logging.WARNING if estimate.verdict in ('disagrees', 'suspect') else logging.INFO
    log.log(level, '%s: %s', sequence.name, estimate.message())
    return config, estimate
