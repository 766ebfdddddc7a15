"""The poses stage's settings: :class:`PosesConfig`, every option and tuning constant of registration, the model's
checks and the cube's calibration (each a documented field), and the stage's fixed names.

Example:
    >>> cfg = PosesConfig(matcher="exhaustive")
    >>> cfg.cube().size, cfg.sfm_options().max_features
    (10.0, 2048)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from plantsplat.cube import CubeSpec
from plantsplat.poses.sfm import SfmConfig

MIN_FRAMES = 3
"""Structure from motion needs at least this many frames."""
WORK_DIR = ".plantsplat/colmap"
"""The stage's working folder in the workspace (COLMAP database, vocabulary, intermediate models)."""
POSES_VERSION = 2
"""Version of the ``poses.json`` report."""
GUIDED_DATABASE = "database_guided.db"
"""In ``WORK_DIR``: the database whose weakly held frames' pairs were matched again, guided (:mod:`plantsplat.poses.guided`)."""
LOGGED_NAMES = 10
"""Log messages that list frames name at most this many."""


@dataclass
class PosesConfig:
    """Options of the poses stage."""

    matcher: Literal["auto", "retrieval", "exhaustive"] = "auto"
    """Pairs to match: retrieval (video neighbours + visually similar frames), exhaustive (every pair), auto
    (exhaustive up to --exhaustive-max-frames frames, else retrieval)."""
    mapper: Literal["auto", "incremental", "global"] = "auto"
    """COLMAP mapper: incremental (frames missing at first are matched again and mapping continues), global (global
    mapping, then incremental mapping continued from it), or auto (both; the model its own matches contradict least)."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "RADIAL"
    """COLMAP camera model shared by all frames (phones: RADIAL)."""
    distortion: Literal["auto", "fit"] = "auto"
    """The camera model's lens distortion: ``auto`` fits it only where the frames support it (BIC,
    :mod:`plantsplat.poses.distortion`), else sets it to zero; ``fit`` always fits it, as COLMAP does."""
    ba_loss_px: float = 1.0
    """Scale (px) of the Cauchy loss on reprojection errors in the bundle adjustments after mapping (the points
    triangulated again, the distortion test, the cube's): errors well above it weigh less."""
    max_features: int = 2048
    """SIFT features per frame."""
    sift_first_octave: int = -1
    """SIFT first octave: -1 upsamples frames 2x (more small features, COLMAP's default); 0 is faster."""
    video_window: int = 3
    """Retrieval matching: each frame is matched with this many following frames of the video."""
    retrieval_neighbours: int = 20
    """Retrieval matching: each frame is matched with this many frames most alike in visual words."""
    vocabulary_words: int = 1024
    """Retrieval matching: words of the visual vocabulary learned from the capture."""
    exhaustive_max_frames: int = 50
    """With --matcher auto, captures of up to this many frames match every pair."""
    import_colmap: Path | None = None
    """Use this COLMAP model (folder with cameras/images/points3D, .bin or .txt) instead of running SfM."""
    import_transforms: Path | None = None
    """Use this nerfstudio transforms.json instead of running SfM."""
    calibrate: bool = True
    """Calibrate scale, gravity and origin with the ArUco cube (--no-calibrate keeps the model as it is)."""
    max_residual_px: float = 3.0
    """Marker detections reprojecting worse than this (pixels) are left out of the calibration; the cube check uses it."""
    cube_bundle_adjustment: bool = True
    """After calibration, bundle-adjust with the cube's marker corners as fixed control points (SfM only)."""
    min_registered: float = 0.7
    """Fail (exit code 3) when fewer than this share of the frames is registered and on the camera's path."""
    warn_registered: float = 0.95
    """Warn (the run goes on with the frames it could use) when fewer than this share is registered."""
    min_cube_frames: float = 0.1
    """Warn when the cube's markers are found in fewer than this share of the frames."""
    max_camera_cube_px: float = 15.0
    """A camera whose own marker detections the calibrated cube misses by more than this (px, RMS) is wrong: it is
    left out."""
    max_path_deviation: float = 0.3
    """A camera off the path of its video neighbours by more than this share of the step to them (or of twice
    their turn) is left out."""
    max_off_path_block: float = 0.1
    """The longest stretch of consecutive frames (share of the frames, at least 4) checked as a block that agrees with
    itself but was posed somewhere off the path of the frames around it."""
    max_scale_disagreement: float = 0.03
    """Fail when the cube's scale from the two halves of the video differs by more than this share."""
    max_face_offset_cm: float = 0.3
    """Fail when the SfM points on a face of the cube lie farther than this from the face's plane."""
    max_facing_away_deg: float = 60.0
    """A camera whose optical axis turns more than this (degrees) away from the point every camera looks at is left
    out (:func:`plantsplat.poses.checks.facing_away`)."""
    max_off_path_share: float = 0.2
    """At most this share of the frames is left out one by one as off the camera's path
    (:func:`plantsplat.poses.checks.off_path`)."""
    missing_pair_neighbours: int = 12
    """A frame missing from the first model is matched again with this many registered cameras nearest to each of
    its registered video neighbours (:func:`plantsplat.poses.pairs.pairs_for_missing`)."""
    weak_frame_share: float = 0.5
    """Registered frames holding fewer of the model's points than this share of the median frame's have their
    verified pairs matched again with guided matching, the points are made again from them, and the points such a
    frame shares with one other frame only are left out (:mod:`plantsplat.poses.guided`); 0 turns it off."""
    face_band_cm: float = 0.6
    """The cube-face check uses the SfM points within this distance (cm) of a face's plane..."""
    face_margin_cm: float = 0.7
    """... and at least this far (cm) inside the face's edges (a silhouette's points are not on the face)..."""
    face_min_points: int = 10
    """... on faces with at least this many such points (:func:`plantsplat.poses.checks.face_offsets`)."""
    cube_size: float = CubeSpec.size
    """Cube edge (cm)."""
    marker_size: float = CubeSpec.marker_size
    """Marker side, black border included (cm)."""
    dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the cube's markers."""
    max_pair_error_px: float = 4.0
    """A matched pair whose inliers lie farther than this (median Sampson distance, px) from the epipolar geometry the
    model gives the two frames is contradicted by the model (--mapper auto keeps the model with the fewest)."""
    mapper_keep_share: float = 0.95
    """With --mapper auto, only models keeping at least this share of the most frames any mapper keeps on the cameras' path
    compete on consistency."""
    mapper_switch_sigma: float = 3.0
    """With --mapper auto, a model other than the incremental mapper's is kept only when the matched pairs the
    incremental model contradicts and it does not outnumber the reverse by this many standard deviations."""
    num_threads: int = 2
    """CPU threads of feature extraction, and processes of matching (each on one thread, its own share of the pairs);
    above one, global mapping runs in a process of its own beside the incremental mapper. k-means, retrieval and each
    mapper run on one thread: the same frames give the same cameras whatever this is."""
    seed: int = 0
    """Random seed (COLMAP's RANSAC and mapper)."""
    colmap_log: bool = False
    """Show COLMAP's own log on stderr (also on with the global --verbose)."""

    def cube(self) -> CubeSpec:
        """The calibration cube these options describe."""
        return CubeSpec(size=self.cube_size, marker_size=self.marker_size, dictionary=self.dictionary)

    def sfm_options(self) -> SfmConfig:
        """The options of :mod:`plantsplat.poses.sfm` (COLMAP's feature extraction, matching and mappers)."""
        return SfmConfig(camera_model=self.camera_model, max_features=self.max_features,
                          first_octave=self.sift_first_octave, num_threads=self.num_threads, seed=self.seed,
                          verbose=self.colmap_log, ba_loss_px=self.ba_loss_px)
