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

The verdict also says how much of the points' global scale the fusion took
(``fusion/shared_scale.py``: the share their shared std leaves them against the single view,
evidence ``scale`` and ``scale_weight``). The adaptation trains on the points moved as the
fusion moved them (:func:`points_scale`): a bias every point shares (an unverified focal length
under rotation) is otherwise learnt by the network, which the fusion then cannot keep apart from
the scene (docs/adaptation.md, "The scale the fusion took").
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, NamedTuple

from ..fusion.shared_scale import points_factor

#: The guard's verdicts under which it trusted none of the keyframe's points.
UNTRUSTED_DECISIONS = frozenset({'single_view'})


class FusionTrust(NamedTuple):
    """What the adaptation takes from the fusion's verdict on a keyframe (the assembler's
    ``trust`` part): why it trusted none of the points ('' when it did), and the factor it
    moved them by (:func:`points_scale`)."""

    untrusted: str = ''
    points_scale: float = 1.0


#: A keyframe trained on as it is: no verdict (no fusion_node, ``follow_fusion_guard`` off), or
#: one that trusted the points and moved nothing.
AS_IS = FusionTrust()


def untrusted_reason(decision: str, reason: str = '', withheld: bool = False) -> str:
    """The skip reason for a keyframe the guard did not trust ('' when it did): ``decision``
    and ``reason`` as ``fused/decision`` or ``FusionResult`` say them."""
    if decision not in UNTRUSTED_DECISIONS and not withheld:
        return ''
    said = f'{decision}: {reason}' if reason else decision
    return f'the fusion trusted none of its points ({said})'


def points_scale(evidence: Mapping[str, Any] | None) -> float:
    """The factor the fusion moved the keyframe's points by (``fusion.shared_scale.points_factor``
    of the guard's evidence ``scale`` and ``scale_weight``; 1 where the evidence does not say)."""
    if not evidence:
        return 1.0
    try:
        scale, weight = float(evidence.get('scale')), float(evidence.get('scale_weight'))
    except (TypeError, ValueError):
        return 1.0
    return points_factor(scale, weight)


def fusion_trust(
    decision: str, reason: str = '', withheld: bool = False, evidence: Mapping[str, Any] | None = None
) -> FusionTrust:
    """What the adaptation takes from a verdict, as ``fused/decision`` or a ``FusionResult``
    say it: :func:`untrusted_reason` and :func:`points_scale`."""
    return FusionTrust(untrusted_reason(decision, reason, withheld), points_scale(evidence))


def trust_from_json(text: str) -> tuple[int, FusionTrust]:
    """``(stamp_ns, FusionTrust)`` of one ``fused/decision`` message (fusion_node's
    ``decision_json``, :func:`fusion_trust`); ``ValueError`` for one that does not say the stamp
    and the decision."""
    try:
        verdict: Any = json.loads(text)
        stamp_ns = int(verdict['stamp_ns'])
        decision = str(verdict['decision'])
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f'unreadable fusion decision: {exc!r}') from None
    reason = str(verdict.get('reason') or '')
    evidence = verdict.get('evidence')
    evidence = evidence if isinstance(evidence, dict) else None
    return stamp_ns, fusion_trust(decision, reason, bool(verdict.get('withheld')), evidence)
