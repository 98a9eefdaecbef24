"""What a check may do with what it finds (``mode``): nothing, say it, or also correct it.

Shared by the calibration checks (``multiview/*_check.py``) and the fusion's stream scale
(``fusion/stream_scale.py``), so one spelling and one YAML quirk hold for all of them.
"""

from __future__ import annotations

#: What a check may do: nothing, say it, or also correct what it found.
CHECK_MODES = ('off', 'warn', 'correct')


def check_mode(section: str, mode: object) -> str:
    """A check's ``mode``, validated; YAML 1.1 reads an unquoted ``mode: off`` (or ``--set
    ...=off``) as false, which is off."""
    if mode is False:
        return 'off'
    if mode not in CHECK_MODES:
        raise ValueError(f'{section}.mode: {mode!r} is not one of {", ".join(CHECK_MODES)}')
    return str(mode)
