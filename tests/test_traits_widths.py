"""The widths' bounds (:mod:`plantsplat.traits.widths`): how far a crown's PCA axes can turn with its sampling."""

from __future__ import annotations

import numpy as np
import pytest

from plantsplat.traitdefs import pca_widths
from plantsplat.traits.widths import anisotropy, axis_turn_deg, even_sample, footprint_range, width_bounds


def _arm(rng, angle_deg, length, n):
    """A leaf lying flat from the crown along ``angle_deg``: points on a 2 cm wide strip ``length`` cm long."""
    a = np.radians(angle_deg)
    t, w = rng.uniform(0, length, n), rng.uniform(-1.0, 1.0, n)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    xy = np.outer(t, u) + np.outer(w, v)
    return np.column_stack([xy, rng.uniform(10.0, 10.5, n)])


def _cross(rng, dense_x: int, n=3000):
    """Four equal leaves at right angles (a round crown); the two along x carry ``dense_x`` times the points."""
    return np.concatenate([_arm(rng, a, 15.0, n * (dense_x if a in (0, 180) else 1)) for a in (0, 90, 180, 270)])


def test_anisotropy_is_the_eigen_gap_at_twice_the_axis_angle():
    rng = np.random.default_rng(0)
    xy = rng.normal(size=(20000, 2)) * [3.0, 1.0]
    a30 = np.radians(30)
    R = np.array([[np.cos(a30), -np.sin(a30)], [np.sin(a30), np.cos(a30)]])
    pts = np.column_stack([xy @ R.T, np.zeros(len(xy))])
    a = anisotropy(pts)
    assert np.linalg.norm(a) == pytest.approx(8.0, rel=0.05)  # 3^2 - 1^2
    assert np.degrees(np.arctan2(a[1], a[0])) / 2 == pytest.approx(30.0, abs=1.0)


def test_an_elongated_crown_has_fixed_axes_and_narrow_bounds():
    rng = np.random.default_rng(1)
    pts = np.concatenate([_arm(rng, a, L, 4000 if a in (0, 180) else 1500) for a, L in ((0, 20), (180, 20), (90, 6), (270, 6))])
    turn = axis_turn_deg(pts, 0.5)
    assert turn < 5.0
    (lo1, hi1), (lo2, hi2) = width_bounds(pts, turn, scale_se=0.0)
    w1, w2 = pca_widths(pts)
    assert lo1 <= w1 <= hi1 and lo2 <= w2 <= hi2
    assert max(w1 - lo1, hi1 - w1) / w1 < 0.02 and (hi2 - lo2) / w2 < 0.25


def test_a_round_crown_sampled_unevenly_has_free_axes_and_bounds_that_cover_every_direction():
    """A cross of four equal leaves whose two leaves along x carry three times the points: their PCA says x is the
    major axis (width 1 = 30 cm), an even sample of the same surface has no major axis; a sampling that favoured the
    other leaves would take the widths along y, or along a diagonal (21 cm). The bounds cover all of it."""
    rng = np.random.default_rng(2)
    pts = _cross(rng, dense_x=3)
    even = even_sample(pts, 0.5)
    assert np.linalg.norm(anisotropy(even)) < 0.2 * np.linalg.norm(anisotropy(pts))
    turn = axis_turn_deg(pts, 0.5)
    assert turn == 90.0
    (lo1, hi1), (lo2, hi2) = width_bounds(pts, turn, scale_se=0.0)
    assert pca_widths(pts)[0] == pytest.approx(30.0, abs=0.5)
    diagonal = 2 * 15.0 * np.cos(np.radians(45)) + 2.0 * np.cos(np.radians(45))  # the cross seen along 45 degrees
    assert lo1 == pytest.approx(diagonal, rel=0.03) and hi1 == pytest.approx(30.0, abs=0.5)
    assert lo2 == pytest.approx(diagonal, rel=0.03) and hi2 == pytest.approx(30.0, abs=0.5)


def test_bounds_widen_with_the_scale_error_and_are_repeatable():
    rng = np.random.default_rng(3)
    pts = _cross(rng, dense_x=2)
    turn = axis_turn_deg(pts, 0.5)
    assert turn == axis_turn_deg(pts.copy(), 0.5)
    (lo, hi), _ = width_bounds(pts, turn, scale_se=0.0)
    (lo_s, hi_s), _ = width_bounds(pts, turn, scale_se=0.01)
    assert lo_s == pytest.approx(lo * 0.98) and hi_s == pytest.approx(hi * 1.02)
    assert width_bounds(pts, 0.0, None)[0] == pytest.approx((pca_widths(pts)[0],) * 2)


def test_bounds_span_the_gaussians_footprint_from_one_to_three_sigma():
    """Issue 40. Sampled at 2 standard deviations, the outermost Gaussians of a crown stop short of its outline, which
    lies within their footprint: the bounds from 1 to 3 standard deviations hold it, the 2-sigma samples alone do
    not."""
    rng = np.random.default_rng(3)
    centres = _arm(rng, 0.0, 30.0, 4000)  # an elongated crown's Gaussians, 30 cm long
    sigma = 0.25  # cm, round Gaussians
    ends = np.concatenate([centres + s * 2 * sigma * np.eye(3)[j] for j in range(3) for s in (1, -1)])
    points, owner = np.concatenate([centres, ends]), np.tile(centres, (7, 1))
    true_width = np.ptp(centres[:, 0]) + 2 * 2.5 * sigma  # the outline at 2.5 sigma, between the two
    inner, outer = footprint_range(points, owner, extent_sigma=2.0)
    assert np.allclose(inner[len(centres):] - owner[len(centres):], (points - owner)[len(centres):] / 2)
    (lo, hi), _ = width_bounds(points, 0.0, None)
    assert hi < true_width  # the 2-sigma samples alone: both ends short of the outline
    (lo, hi), _ = width_bounds(points, 0.0, None, inner=inner, outer=outer)
    assert lo < true_width < hi and hi - lo == pytest.approx(2 * 2 * sigma, rel=0.05)
