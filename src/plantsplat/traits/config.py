"""The traits stage's settings: :class:`TraitsConfig`, the one source of every option and tuning constant of the
measurement (each a documented field), and the calibration cube's edge they measure with.

Example:
    >>> TraitsConfig().opacity_min, cube_edge_cm(TraitsConfig(cube_size_cm=20.0), None)
    (0.1, 20.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plantsplat.cube import CubeSpec

ROBUST_KEYS = ("height_cm", "height_extent_cm", "width1_cm", "width2_cm")
"""The traits also given from trimmed quantiles (``robust`` in ``traits.json``)."""


@dataclass
class TraitsConfig:
    """Settings of the trait measurement (all lengths in cm unless said otherwise)."""

    opacity_min: float = 0.1
    """Keep Gaussians whose opacity is at least this (the paper's culling threshold tau_alpha)."""
    max_scale_cm: float | None = None
    """Drop Gaussians whose largest extent exceeds this (cm; calibrated clouds only). None: keep all."""
    eps: float | None = None
    """DBSCAN radius in the cloud's units (cm when calibrated). None: from the point spacing."""
    eps_factor: float = 3.0
    """Automatic radius = this times the median distance to the min_points-th neighbour."""
    eps_min_cm: float = 0.4
    """Lower bound of the automatic radius on calibrated clouds (cm)."""
    eps_max_cm: float = 2.0
    """Upper bound of the automatic radius on calibrated clouds (cm)."""
    min_points: int = 10
    """DBSCAN minimum neighbourhood size."""
    max_cluster_points: int = 250_000
    """Cluster at most this many points (a random subset; the rest take their neighbour's label)."""
    merge_distance_cm: float | None = None
    """None: every cluster that is not the cube, below the ground or a floater is plant (the masks decided the
    object in 3D, so what the model holds is plant; leaves on petioles too thin to reconstruct are apart from
    the crown). A distance (cm): only the clusters linked to the plant by gaps up to it (for clouds made
    without such masks)."""
    min_cluster_fraction: float = 0.002
    """Clusters smaller than this fraction of the main plant cluster are floaters."""
    fruit_join_cm: float = 15.0
    """Clusters left out as far from the plant join it when they are mostly fruit-coloured, lie within this distance
    of the plant and no higher than its top: fruit hang on peduncles too thin to be reconstructed."""
    fruit_join_fraction: float = 0.5
    """Share of fruit-coloured points that makes a cluster a hanging fruit."""
    fruit_join_unripe_cm: float = 7.0
    """Unripe fruit and trusses of ripe and unripe fruit join the same way: clusters mostly of red or unripe-fruit
    colour (pale yellow-green to cream, the segmenter's colour model) no thicker than this (cm) and no longer than
    twice it (the segmenter's ``unripe_fruit_cm``), since walls, boxes and pots share the unripe colour; 0: only
    mostly red clusters join."""
    trim: float = 0.0005
    """Robust height/widths use the trim .. 1-trim quantiles instead of min .. max (0.0005: the ~0.05 % most
    extreme points on each side are ignored)."""
    cube_size_cm: float | None = None
    """Edge of the calibration cube (cm). Default: the cube the poses stage measured with (its record in
    markers.json, from --poses.cube-size), else the cube's default (:class:`~plantsplat.cube.CubeSpec`)."""
    scale_tolerance_pct: float = 3.0
    """Flag the result when ArUco and cube-plane scales disagree by more than this (%)."""
    max_tilt_deg: float = 3.0
    """Flag the result when the cube's vertical and the frame's z differ by more than this (deg)."""
    fruit_hue_deg: float = 12.0
    """Fruit colour: hue within this many degrees of red."""
    fruit_min_saturation: float = 0.45
    """Fruit colour: minimum HSV saturation (0..1)."""
    fruit_min_value: float = 0.2
    """Fruit colour: minimum HSV value (0..1)."""
    fruit_eps_cm: float = 0.6
    """DBSCAN radius for grouping fruit-coloured points into fruit (cm)."""
    fruit_min_points: int = 15
    """Minimum points of one fruit."""
    fruit_min_size_cm: float = 0.8
    """Minimum extent of one fruit (cm)."""
    fruit_views: bool = True
    """Count as one fruit the pieces of red surface that the workspace's frames show as one red region (a fruit
    seen past petioles falls into pieces in the model). Off: each piece is counted."""
    extent_sigma: float = 2.0
    """0: measure the Gaussians' centres (the paper). > 0: also use the 6 ends of each Gaussian's principal
    axes at this many standard deviations (read from export/splat.ply), so that the Gaussians' extents count:
    a reconstruction's Gaussians sit inside the surfaces they draw, so their centres underestimate every trait."""
    cube_edge: Literal["auto", "planes", "envelope"] = "auto"
    """How the cube's edge is measured: 'planes' (mean distance between opposite faces' fitted planes: exact on
    surface samples), 'envelope' (the 1 %..99 % extent of the cube's points along its axes: Gaussian
    reconstructions, whose faces' planes lie inside the faces) or 'auto' (envelope for Gaussians, that is when
    opacities or extent samples come with the points; planes otherwise)."""
    seed: int = 0
    """Random seed (subsampling, RANSAC)."""


def cube_edge_cm(s: TraitsConfig, cube: CubeSpec | None) -> float:
    """The cube's edge (cm): ``s.cube_size_cm`` when given, else the recorded ``cube``'s, else the default cube's.

    Example:
        >>> cube_edge_cm(TraitsConfig(), CubeSpec(size=20.0, marker_size=19.2)), cube_edge_cm(TraitsConfig(), None)
        (20.0, 10.0)
    """
    return float(s.cube_size_cm) if s.cube_size_cm is not None else float((cube or CubeSpec()).size)


@dataclass(frozen=True)
class MeasureConfig:
    """How the plant is told from the rest of the cloud beside the cube fit (:mod:`plantsplat.traits.measure`). Not
    options: the values the traits benchmark (``benchmarks/bench_traits.py``) and the foreign renders were measured
    with."""

    cube_axes_tolerance: float = 0.03
    """Flag the result when the cube's edges between opposite faces differ from one axis to another by more than this
    share of their mean (the axes whose two faces are both seen: :meth:`plantsplat.traits.cube_fit.CubeFit.axis_spread`):
    the cube is distorted in the reconstruction."""
    below_ground_quantile: float = 0.9
    """A cluster is under the ground when it lies wholly below z = 0, or this quantile of its heights lies more than a
    centimetre below it (the Gaussians' ends reach a little under what they draw)."""
    fragment_ratio: int = 20
    """A cluster nearer the cube's box than the plant's body is a piece of the cube when it holds less than 1/this of
    the body's points."""
    fragment_reach: float = 0.25
    """A cluster is a piece of the cube only when its median point lies within this share of the cube's edge of the
    cube's box (2.5 cm for the 10 cm cube): the cube's Gaussians draw its faces, not the air around it."""
    even_cell_cm: float = 0.5
    """Cell of the grid the plant is resampled evenly on to see how far its PCA axes turn with the sampling (the
    widths' bounds, :mod:`plantsplat.traits.widths`)."""
    body_sample: int = 20000
    """The plant body's points that cube fragments are compared with: a random subset of at most this many."""
    min_plant_points: int = 50
    """A plant of fewer points than this is not measured (the reconstruction is too sparse)."""


@dataclass(frozen=True)
class CubeFitConfig:
    """How the calibration cube is recognised among the clusters and measured (:mod:`plantsplat.traits.cube_fit`).
    Lengths are shares of the cube's edge unless said otherwise; the values are those the traits benchmark
    (``benchmarks/bench_traits.py``) and the foreign renders were measured with."""

    extent_quantile: float = 0.01
    """Robust extents of a cluster: between this quantile and its complement along each axis (stray points)."""
    pca_max_ratio: float = 2.5
    """Quick rejection: a cube's extents along any three orthogonal axes agree within sqrt(3); a cluster whose
    shortest PCA extent is less than its longest over this is not a cube."""
    pca_size_range: tuple[float, float] = (0.5, 2.2)
    """Quick rejection when the cube's size is known: its longest PCA extent lies within these multiples of it."""
    pca_sample: int = 5000
    """Points of a cluster used for its PCA axes."""
    orientation_sample: int = 4000
    """Points used to fit the face planes that orient a candidate's box."""
    orientation_planes: int = 6
    """Planes fitted to orient a candidate's box (one per face)."""
    core_share: float = 0.95
    """A candidate's core: its points nearest its median, without attached floaters."""
    surface_band: float = 0.08
    """A point lies on the box's surface within this share of its size (a reconstructed cube is a hollow shell)."""
    face_min_points: int = 16
    """Fewest points on a face for its coverage to be judged."""
    face_grid: int = 4
    """A face's coverage is judged on this many cells along each side."""
    face_cover: float = 0.6
    """A face is covered when this share of its cells hold points."""
    min_equality: float = 0.75
    """Accept: the box's shortest extent at least this share of its longest."""
    min_surface: float = 0.6
    """Accept: at least this share of the points on the box's surface."""
    size_range: tuple[float, float] = (0.75, 1.35)
    """Accept, when the cube's size is known: the box's mean extent within these multiples of it."""
    parallel_deg: float = 12.0
    """Face planes whose normals are within this angle are one direction; three directions must be this close
    to orthogonal."""
    plane_threshold: float = 0.02
    """RANSAC's inlier distance, as a share of the edge, when none is given."""
    plane_min_points: int = 30
    """Fewest points of a plane (and at least ``plane_min_share`` of the cluster's)."""
    plane_min_share: float = 0.03
    """Smallest share of the cluster's points a plane must hold."""
    inlier_band: float = 2.5
    """A point belongs to a plane within this many RANSAC thresholds."""
    refit_min_points: int = 10
    """Fewest points to refit a plane by least squares."""
    fit_min_points: int = 60
    """Fewest points of a cluster to fit a cube to."""
    duplicate_share: float = 0.2
    """Planes of one direction closer than this share of the edge are fits of the same face."""
    face_min_share: float = 0.1
    """A face counts when it holds at least this share of the best face's inliers (and ``plane_min_points``)."""
    face_reach: float = 1.05
    """A face's points lie within this multiple of half the edge across it."""
    up_camera_share: float = 0.9
    """Up from the cameras: confident when this share of the cameras lie above the chosen ground and less
    above any other."""
    up_bottom_ratio: float = 0.3
    """Up from the unseen bottom face: confident when it holds under this share of its opposite face's points."""
