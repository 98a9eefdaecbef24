"""Whether the fusion's guard trusted a keyframe's multi-view points: the adaptation learns only
from keyframes it did.

Why: the adaptation and the fusion read the same points, but only the fusion's guard sees
how they fit the single view and each other (RANSAC support, the local agreement, the fit's
residual: fusion/guard.py). The adaptation's own tests (the points' std, their coverage, a
held-out paired test of each update) judge an update on points of the same kind, so points that
are wrong together pass them. 7-Scenes 0-499 with its poses given inverted (the world's pose
in the camera, T_cw, where the camera's in the world is meant) was fused to the single view on
93 of 98 keyframes (`single_view`: the guard trusted none of the points), yet the adaptation
trained on them and made the single view itself 0.975 m against the shipped network's 0.511
(docs/adaptation.md, "Keyframes the guard did not trust"). A keyframe whose verdict is
``single_view`` (none of its points trusted) or withheld is therefore not trained on; the
other verdicts trust at least the points' scale.

The verdict is the fusion's of the single view as it was predicted for that keyframe, so it
is the same prequential order the adaptation already keeps (keyframe k is predicted before
it is trained on).
"""

from __future__ import annotations

import json
from typing import Any

#: The guard's verdicts under which it trusted none of the keyframe's points.
UNTRUSTED_DECISIONS = frozenset({'single_view'})


def untrusted_reason(decision: str, reason: str = '', withheld: bool = False) -> str:
    """The skip reason for a keyframe the guard did not trust ('' when it did): ``decision``
    and ``reason`` as ``fused/decision`` or ``FusionResult`` say them."""
    if decision not in UNTRUSTED_DECISIONS and not withheld:
        return ''
    said = f'{decision}: {reason}' if reason else decision
    return f'the fusion trusted none of its points ({said})'


def verdict_from_json(text: str) -> tuple[int, str]:
    """``(stamp_ns, untrusted reason)`` of one ``fused/decision`` message (fusion_node's
    ``decision_json``); ``ValueError`` for one that does not say them."""
    try:
        verdict: Any = json.loads(text)
        stamp_ns = int(verdict['stamp_ns'])
        decision = str(verdict['decision'])
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f'unreadable fusion decision: {exc!r}') from None
    reason = str(verdict.get('reason') or '')
    return stamp_ns, untrusted_reason(decision, reason, bool(verdict.get('withheld')))
