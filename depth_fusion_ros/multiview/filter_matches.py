"""One frame's matches into the filter's keyframe: measurements, outlier votes, resets.

Step 2's last part (``filter_frame_update``): after the searches, each searched row's match
either updates its estimate (``filter_update``'s Gaussian x uniform update; a row without an
estimate takes it as its first measurement), or, for a row with an estimate that matched
nothing, is an outlier vote; a row whose inlier ratio falls below ``min_inlier_ratio`` goes
back to "no estimate". Only the rows that change are read and written.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..true_indices import true_indices
from .filter_config import FilterConfig
from .filter_keyframe import FilterKeyframe, no_estimate
from .filter_update import BetaGaussian, gaussian_uniform_update, outlier_vote
from .native_apply import native_apply_matches

if TYPE_CHECKING:
    from .filter import DepthFilter


def measurement_variance(
    config: FilterConfig, rho: torch.Tensor, j: torch.Tensor, baseline: float
) -> torch.Tensor:
    """Measurement variance: one ``pixel_sigma`` of matching error back-propagated through the
    epipolar motion ``j``, plus the pose noise as a relative error ``pose_sigma / baseline``."""
    c = config
    tau2 = (c.pixel_sigma / torch.clamp(j, min=1e-6)) ** 2
    if c.pose_sigma == 0.0:  # the default: the term is + 0 (its three passes were a tenth of an update)
        return tau2
    return tau2 + (rho * (c.pose_sigma / baseline)) ** 2


@dataclass
class Matches:
    """One frame's searches, per searched keyframe row: the row, the match ``x`` (inverse
    depth), the epipolar motion ``j_x`` there, the match's cost, and whether the row had no
    prior (``fresh``)."""

    rows: torch.Tensor
    x: torch.Tensor
    j_x: torch.Tensor
    cost: torch.Tensor
    fresh: torch.Tensor

    def take(self, index: torch.Tensor) -> Matches:
        """These searches at ``index`` (into the searched rows) only."""
        fields = (self.rows, self.x, self.j_x, self.cost, self.fresh)
        return Matches(*(t.index_select(0, index) for t in fields))


def apply_matches(
    filt: DepthFilter, key: FilterKeyframe, matches: Matches, valid: torch.Tensor, baseline: float
) -> None:
    """One frame's matches into the keyframe's state, in place; ``valid``: which searched
    rows found a measurement.

    Only the rows that change are touched: a valid match updates its row (or gives a row
    without a prior its first measurement), a row with a prior that matched nothing gets an
    outlier vote, and a row without a prior that matched nothing is left as it is. The same
    numbers as computing every searched row's posterior and keeping the valid ones with
    ``where`` (:func:`_apply_dense`, the form until 2026-12-02 and still the GPU's;
    ``test_matches_update_only_the_rows_they_change``), at about half of the update's passes
    on CPU, where ``where`` is several times slower than arithmetic and the posterior is
    needed for half of the rows.
    """
    if matches.rows.device.type != 'cpu':
        # On a GPU the two indices below are two host round trips a frame, which the dense
        # form does not need and ``where`` is no slower there than arithmetic: kept as it was.
        _apply_dense(filt, key, matches, valid, baseline)
        return
    if native_apply_matches(filt, key, matches, valid, baseline):  # the same state, in two passes
        return
    _measure(filt, key, matches.take(true_indices(valid)), baseline)
    _vote(filt, key, matches.rows.index_select(0, true_indices(~matches.fresh & ~valid)))


def _apply_dense(
    filt: DepthFilter, key: FilterKeyframe, matches: Matches, valid: torch.Tensor, baseline: float
) -> None:
    """:func:`apply_matches` as it was until 2026-12-02, and still is on a GPU: every searched
    row's posterior, the valid ones kept with ``where``, the outlier votes and resets, one
    scatter per field."""
    c, st = filt.config, key.state
    rows, x, fresh = matches.rows, matches.x, matches.fresh
    pick = lambda t: t.index_select(0, rows)  # noqa: E731
    mu_r, var_r, a_old, b_old = pick(st.mu), pick(st.var), pick(st.a), pick(st.b)
    tau2 = measurement_variance(c, x, matches.j_x, baseline)
    prior = BetaGaussian(mu_r, var_r, a_old, b_old)
    post = gaussian_uniform_update(prior, x, tau2, filt.rho_range)
    mu_n = torch.where(valid, post.mu, mu_r)
    var_n = torch.where(valid, post.var, var_r)
    a_n = torch.where(valid, post.a, a_old)
    b_n = torch.where(valid, post.b, outlier_vote(prior, ~fresh & ~valid).b)
    born = true_indices(fresh & valid)  # first measurements
    if born.numel() > 0:
        mu_n.index_copy_(0, born, x.index_select(0, born))
        var_n.index_copy_(0, born, tau2.index_select(0, born))
        a_n.index_fill_(0, born, c.init_a)
        b_n.index_fill_(0, born, c.init_b)
    n_n = pick(key.updates) + valid.long()
    prior_n = ~fresh | valid
    gone = _outliers(filt, a_n, b_n, ~fresh)
    _reset(filt, gone, (mu_n, var_n, a_n, b_n, n_n, prior_n))
    cost = torch.where(valid, matches.cost, pick(key.cost))
    for target, value in zip(
        (st.mu, st.var, st.a, st.b, key.updates, key.prior, key.cost),
        (mu_n, var_n, a_n, b_n, n_n, prior_n, cost),
        strict=True,
    ):
        target.scatter_(0, rows, value)


def _measure(filt: DepthFilter, key: FilterKeyframe, m: Matches, baseline: float) -> None:
    """The Gaussian x uniform update of the rows of ``m`` (all valid matches) in place; a row
    without a prior takes its first measurement."""
    if m.rows.numel() == 0:
        return
    c, st = filt.config, key.state
    state = lambda t: t.index_select(0, m.rows)  # noqa: E731
    tau2 = measurement_variance(c, m.x, m.j_x, baseline)
    prior = BetaGaussian(state(st.mu), state(st.var), state(st.a), state(st.b))
    post = gaussian_uniform_update(prior, m.x, tau2, filt.rho_range)
    mu_n, var_n, a_n, b_n = post.mu, post.var, post.a, post.b
    born = true_indices(m.fresh)  # first measurements
    if born.numel() > 0:
        mu_n.index_copy_(0, born, m.x.index_select(0, born))
        var_n.index_copy_(0, born, tau2.index_select(0, born))
        a_n.index_fill_(0, born, c.init_a)
        b_n.index_fill_(0, born, c.init_b)
    n_n = state(key.updates).add_(1)
    prior_n = torch.ones_like(m.fresh)
    gone = _outliers(filt, a_n, b_n, ~m.fresh)
    _reset(filt, gone, (mu_n, var_n, a_n, b_n, n_n, prior_n))
    for target, value in zip(
        (st.mu, st.var, st.a, st.b, key.updates, key.prior, key.cost),
        (mu_n, var_n, a_n, b_n, n_n, prior_n, m.cost),
        strict=True,
    ):
        target.scatter_(0, m.rows, value)  # rows are distinct: index_copy_'s result, a third cheaper


def _vote(filt: DepthFilter, key: FilterKeyframe, at: torch.Tensor) -> None:
    """An outlier vote (``b += 1``, ``filter_update.outlier_vote``) for the keyframe rows ``at``:
    visible, with a prior, and nothing matched; in place."""
    if at.numel() == 0:
        return
    st = key.state
    b_n = st.b.index_select(0, at).add_(1.0)
    st.b.scatter_(0, at, b_n)
    gone = at.index_select(0, _outliers(filt, st.a.index_select(0, at), b_n))
    _reset(filt, gone, (st.mu, st.var, st.a, st.b, key.updates, key.prior))


def _outliers(
    filt: DepthFilter, a: torch.Tensor, b: torch.Tensor, with_prior: torch.Tensor | None = None
) -> torch.Tensor:
    """Indices whose inlier ratio ``a / (a + b)`` fell below ``min_inlier_ratio`` (only among
    ``with_prior`` when given): to be reset to "no estimate" (they may be re-seeded)."""
    low = a / (a + b) < filt.config.min_inlier_ratio
    return true_indices(low if with_prior is None else with_prior & low)


def _reset(filt: DepthFilter, gone: torch.Tensor, values: tuple[torch.Tensor, ...]) -> None:
    """Rows ``gone`` of the mean, variance, ``a``, ``b``, count and prior flag ``values`` back to
    "no estimate" (``filter_keyframe.no_estimate``), in place."""
    if gone.numel() > 0:
        for value, fill in zip(values, no_estimate(filt), strict=True):
            value.index_fill_(0, gone, fill)
