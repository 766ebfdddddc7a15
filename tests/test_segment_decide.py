"""The 3D decision of the plant: minimum cut against brute force, and constructed scenes (no rendering)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plantsplat.segment.decide import DecideConfig, decide_plant, min_cut_labels, pieces


def _energy(labels: np.ndarray, unary: np.ndarray, i: np.ndarray, j: np.ndarray, w: np.ndarray) -> float:
    """The cut's cost written out: a node off its favoured side pays |unary|; a cut edge pays its weight."""
    cost = np.where(labels, np.maximum(-unary, 0), np.maximum(unary, 0)).sum()
    return float(cost + w[labels[i] != labels[j]].sum())


@pytest.mark.parametrize("seed", range(6))
def test_min_cut_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 9
    unary = rng.normal(0, 1.5, n)
    i, j = np.array(list(itertools.combinations(range(n), 2))).T
    pick = rng.random(len(i)) < 0.4
    i, j, w = i[pick], j[pick], rng.uniform(0, 2, pick.sum())
    got = min_cut_labels(unary, i, j, w)
    best = min(_energy(np.array(b, bool), unary, i, j, w) for b in itertools.product([0, 1], repeat=n))
    assert _energy(got, unary, i, j, w) == pytest.approx(best, abs=0.02)  # capacities rounded to 1/1000


def test_smoothness_carries_an_undecided_node_with_its_neighbours():
    unary = np.array([3.0, 3.0, -0.2, 3.0])  # node 2 leans to "not" a little; its neighbours are sure
    i, j = np.array([0, 1, 2]), np.array([2, 2, 3])
    assert min_cut_labels(unary, i, j, np.full(3, 1.0)).all()
    assert min_cut_labels(unary, i, j, np.zeros(3)).tolist() == [True, True, False, True]


def _scene(rng):
    """A green plant (stem and a disc of leaves) above a pot, a grey wall patch hung above it, a green piece 25 cm
    away, white flowers on the leaves, and the white room and brown pot around. Returns ``(mu, rgb, weight,
    candidate, rest, truth)``."""
    stem = np.c_[rng.normal(0, 0.2, (300, 2)), rng.uniform(15, 25, 300)]
    a, r = rng.uniform(0, 2 * np.pi, 1500), np.sqrt(rng.uniform(0, 1, 1500)) * 12
    leaves = np.c_[r * np.cos(a), r * np.sin(a), 25 + rng.normal(0, 0.5, 1500)]
    flowers = np.concatenate([rng.normal(0, 0.6, (30, 3)) + [x, y, 26.5] for x, y in ((6, 2), (-5, 5), (1, -8))])
    patch = np.c_[rng.uniform(-4, 4, (400, 2)), 36 + rng.normal(0, 0.2, 400)]  # wall-coloured, hung above
    stray = np.c_[rng.normal(25, 0.4, (40, 2)), rng.normal(3, 0.4, 40)]  # green, by the cube, apart from the body
    room = np.c_[rng.uniform(-150, 150, (3000, 2)), rng.uniform(0, 200, 3000)]
    pot = np.c_[rng.normal(0, 8, (600, 2)), rng.uniform(0, 14, 600)]
    def colour(n, mean, sd):
        return np.clip(rng.normal(mean, sd, (n, 3)), 0, 1)

    def green(n):
        return colour(n, [0.25, 0.55, 0.2], 0.05)

    def grey(n):
        return np.clip(rng.normal(0.72, 0.04, (n, 1)) + rng.normal(0, 0.01, (n, 3)), 0, 1)

    def brown(n):
        return colour(n, [0.45, 0.3, 0.2], 0.04)

    mu = np.concatenate([stem, leaves, flowers, patch, stray, room, pot])
    rgb = np.concatenate([green(300), green(1500), grey(90) + 0.2, grey(400), green(40), grey(3000), brown(600)])
    kind = np.repeat([0, 0, 0, 1, 2, 3, 4], [300, 1500, 90, 400, 40, 3000, 600])
    candidate = kind <= 2
    return mu, np.clip(rgb, 0, 1), np.ones(len(mu)), candidate, ~candidate, kind == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_wall_patch_and_a_piece_by_the_cube_are_not_plant_and_white_flowers_are(seed):
    mu, rgb, weight, candidate, rest, truth = _scene(np.random.default_rng(seed))
    plant, facts = decide_plant(mu, rgb, weight, candidate, rest, 45.0)
    assert plant[truth].mean() > 0.99 and not plant[candidate & ~truth].any(), facts
    assert plant[1800:1890].all()  # the white flowers, the colour of the room, stay with their leaves
    position, _ = decide_plant(mu, rgb, weight, candidate, rest, 45.0,
                               cfg=DecideConfig(enabled=True, max_colour_evidence=0.0, gap_scale=1e9))
    assert position[candidate].all()  # without colour and attachment every candidate is plant


def test_a_wall_patch_touching_a_leaf_does_not_teach_the_plant_its_colour():
    """A blank wall patch the quick model hangs against a leaf's edge joins the plant's body. Learned from the whole
    body, the plant's colours include the wall's and the patch stays plant; learned where structure from motion found
    the body (no SfM point on a blank wall), the patch goes and the plant stays."""
    rng = np.random.default_rng(3)
    mu, rgb, weight, candidate, rest, truth = _scene(rng)  # (its own wall patch hangs apart from the body)
    sheet = np.c_[rng.normal(11.0, 0.2, 400), rng.uniform(-4, 4, 400), rng.uniform(25.5, 37, 400)]
    grey = np.clip(rng.normal(0.72, 0.04, (400, 1)) + rng.normal(0, 0.01, (400, 3)), 0, 1)
    mu, rgb = np.concatenate([mu, sheet]), np.concatenate([rgb, grey])
    weight, truth = np.ones(len(mu)), np.concatenate([truth, np.zeros(400, bool)])
    candidate, rest = np.concatenate([candidate, np.ones(400, bool)]), np.concatenate([rest, np.zeros(400, bool)])
    sheet_idx = np.arange(len(mu) - 400, len(mu))
    textured = np.flatnonzero(truth)[::3]  # SfM points on the stem and leaves, none on the wall
    sfm = mu[textured] + rng.normal(0, 0.1, (len(textured), 3))
    sfm_distance = cKDTree(sfm).query(mu)[0]
    whole, facts_whole = decide_plant(mu, rgb, weight, candidate, rest, 45.0)
    taught, facts = decide_plant(mu, rgb, weight, candidate, rest, 45.0, sfm_distance)
    gap, _, _ = pieces(mu[candidate], DecideConfig().attach_reach * 45.0)
    assert (gap[-400:] == 0).all() and whole[sheet_idx].mean() > 0.5, facts_whole  # the patch joined the body
    assert not taught[sheet_idx].any() and taught[truth].mean() > 0.99, facts


def test_pieces_are_measured_from_the_largest():
    rng = np.random.default_rng(1)
    body = rng.normal(0, 3, (2000, 3))
    leaf = rng.normal(0, 0.3, (200, 3)) + [14, 0, 0]  # a leaf whose petiole the model lost
    speck = rng.normal(0, 0.3, (10, 3)) + [0, 30, 0]
    gap, size, label = pieces(np.concatenate([body, leaf, speck]), 2.0)
    assert (gap[:2000] == 0).mean() > 0.97 and 3 < gap[2000:2200].min() < 8 < 20 < gap[2200:].min()
    assert 5 < size < 12
    assert len(set(label[2000:2200])) == 1 and len(set(label[2200:])) == 1 and label[2000] != label[2200]


def test_too_little_evidence_keeps_the_candidates():
    mu = np.random.default_rng(2).normal(0, 1, (50, 3))
    cand = np.ones(50, bool)
    plant, facts = decide_plant(mu, np.full((50, 3), 0.5), np.ones(50), cand, np.zeros(50, bool), 45.0)
    assert plant.all() and "position" in facts["decided_by"]


def test_a_piece_apart_that_no_sfm_point_holds_goes_and_one_that_a_point_holds_stays():
    """Two equal pieces 5 cm beside the plant's leaves, of a colour neither the plant nor the room has (so colour
    decides nothing): structure from motion found points on one of them (a leaf whose petiole the quick model lost),
    none near the other (Gaussians a quick model hung in front of a blank wall)."""
    rng = np.random.default_rng(5)
    mu, rgb, weight, candidate, rest, truth = _scene(rng)
    leaf = np.c_[rng.normal(17.0, 0.4, 30), rng.normal(0, 0.4, 30), rng.normal(25.0, 0.2, 30)]
    floater = leaf * [-1.0, 1.0, 1.0]
    mu = np.concatenate([mu, leaf, floater])
    rgb = np.concatenate([rgb, np.clip(rng.normal([0.1, 0.2, 0.85], 0.02, (60, 3)), 0, 1)])
    n = len(mu)
    weight, candidate = np.ones(n), np.concatenate([candidate, np.ones(60, bool)])
    rest = np.concatenate([rest, np.zeros(60, bool)])
    textured = np.concatenate([np.flatnonzero(truth)[::3], [n - 60 + 3]])  # SfM points on the body and on the leaf
    sfm_distance = cKDTree(mu[textured] + rng.normal(0, 0.05, (len(textured), 3))).query(mu)[0]
    gap, _, _ = pieces(mu[candidate], DecideConfig().attach_reach * 45.0)
    assert (gap[-60:] > 3).all()  # both apart from the body
    plant, facts = decide_plant(mu, rgb, weight, candidate, rest, 45.0, sfm_distance)
    assert plant[n - 60:n - 30].all() and not plant[n - 30:].any(), facts
    assert plant[:len(truth)][truth].mean() > 0.99 and facts["unsupported"] >= 30
    without, _ = decide_plant(mu, rgb, weight, candidate, rest, 45.0)
    assert without[n - 60:].all()  # without SfM points nothing tells the two apart


def test_in_the_pot_over_the_soil_the_body_too_needs_an_sfm_point_near():
    """Issue 40. A quick model blurs a pot's dark soil into half-transparent layers a centimetre or two over it, joined
    to the crown's foot: on the plant's body, and of a colour the plant's dark parts share, so the body's prior keeps
    them. Over the soil (``needs_support``) a Gaussian of the body must lie as near an SfM point as the body's
    Gaussians do: the blur floats over the soil's points and goes, the crown's foot, which SfM holds, stays; the rest
    of the plant does not change."""
    rng = np.random.default_rng(9)
    mu, rgb, weight, candidate, rest, truth = _scene(rng)
    dark = np.array([0.12, 0.08, 0.04])
    foot = np.c_[rng.normal(0, 0.3, (60, 2)), rng.uniform(12.2, 15.0, 60)]  # the crown's foot over the soil at 12
    a, r = rng.uniform(0, 2 * np.pi, 80), rng.uniform(2.0, 6.5, 80)
    blur = np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(13.3, 14.0, 80)]  # 1.3-2 cm over the soil
    a, r = rng.uniform(0, 2 * np.pi, 400), 6.5 * np.sqrt(rng.uniform(0, 1, 400))
    soil = np.c_[r * np.cos(a), r * np.sin(a), rng.normal(12.0, 0.05, 400)]  # SfM points only, no Gaussians
    n0 = len(mu)
    shaded, pot = np.flatnonzero(truth)[::6], rest & (mu[:, 2] < 14.5) & (np.hypot(mu[:, 0], mu[:, 1]) < 30)
    rgb[shaded] = np.clip(rng.normal(dark, 0.02, (len(shaded), 3)), 0, 1)  # the plant's shaded parts and the pot are
    rgb[pot] = np.clip(rng.normal(dark, 0.02, (int(pot.sum()), 3)), 0, 1)  # dark too: colour does not decide
    mu = np.concatenate([mu, foot, blur])
    rgb = np.concatenate([rgb, np.clip(rng.normal(dark, 0.02, (140, 3)), 0, 1)])
    n = len(mu)
    weight, candidate = np.ones(n), np.concatenate([candidate, np.ones(140, bool)])
    rest = np.concatenate([rest, np.zeros(140, bool)])
    sfm = np.concatenate([mu[np.flatnonzero(truth)[::3]], mu[n0:n0 + 60:3], soil])
    sfm_distance = cKDTree(sfm + rng.normal(0, 0.05, sfm.shape)).query(mu)[0]
    over_soil = np.zeros(n, bool)
    over_soil[n0:] = True
    gap, _, _ = pieces(mu[candidate], DecideConfig().attach_reach * 45.0)
    assert (gap[-140:] == 0).all()  # the foot and the blur are on the body
    without, _ = decide_plant(mu, rgb, weight, candidate, rest, 45.0, sfm_distance)
    assert without[n0 + 60:].mean() > 0.9  # the body's prior keeps the blur
    plant, facts = decide_plant(mu, rgb, weight, candidate, rest, 45.0, sfm_distance, needs_support=over_soil)
    assert plant[n0:n0 + 60].all() and plant[n0 + 60:].mean() < 0.1, facts
    assert (plant[:n0] == without[:n0]).all() and facts["unsupported_on_body"] >= 70
