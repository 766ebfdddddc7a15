"""Orchestrates one synthetic capture: scene -> ground truth -> camera path -> frames, masks, video, JSON.

Every random choice comes from ``numpy.random.SeedSequence(seed)`` split into independent streams
(scene, textures, camera, sensor, ground-truth sampling, per-frame noise), so the same seed gives
bit-identical PNGs, PLYs and JSON (rendering is deterministic on a given Mesa build).
"""

from __future__ import annotations

import importlib
import json
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from plantsplat.cube import CubeSpec
from plantsplat.errors import UsageError
from plantsplat.io import write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, progress
from plantsplat.synth import camera as cam
from plantsplat.synth import groundtruth as gt
from plantsplat.synth.config import FORMAT, SynthConfig
from plantsplat.synth.mesh import CLASS_NAMES, CUBE_CLASSES, FOREGROUND_CLASSES
from plantsplat.synth.render import Renderer
from plantsplat.synth.scene import make_scene
from plantsplat.synth.sensor import SensorModel
from plantsplat.synth.textures import make_layers
from plantsplat.synth.video import encode_frames
from plantsplat.traitdefs import TRAIT_KEYS
from plantsplat.workspace import IMAGE_PATTERN, prepare_output_dir

log = get_logger(__name__)
FPS = 24
WORLD_FRAME = ("origin on the ground plane (top of the platform the pot and cube stand on) below the pot centre, "
               "+z up")
CAMERA_CONVENTION = "camera-to-world 4x4, OpenCV camera axes (x right, y down, z forward), cm"
PIXEL_CONVENTION = ("OpenCV: pixel (u, v) has its centre at integer coordinates, u to the right, v down, (0, 0) = "
                    "centre of the top-left pixel; [u, v, 1] ~ K X_cam")
OBJECTS_RULE = ("colour pass of the foreground meshes (plant, cube) alone over black, lit and shadowed as in the "
                "frame, developed without noise, blur, exposure or white-balance drift or vignetting at the capture's "
                "base gain, with the frames' MSAA")
CLASSES_RULE = ("id pass without MSAA (the masks' rule): the class id of the surface seen through the pixel centre, "
                "uint8: " + ", ".join(f"{c} {name}" for c, name in sorted(CLASS_NAMES.items())))
MASK_RULE = ("id pass without MSAA: a pixel is 255 when the surface seen through the pixel centre belongs to the "
             "plant (leaf, petiole, crown, fruit with calyx, peduncle, flower) or the cube, else 0")


def validate(cfg: SynthConfig) -> None:
    """Reject impossible settings with a one-line :class:`UsageError` (exit code 2)."""
    if cfg.width < 64 or cfg.height < 64 or cfg.width > 4096 or cfg.height > 4096:
        raise UsageError(f"--width {cfg.width} --height {cfg.height}: each side must be between 64 and 4096 pixels")
    if cfg.width % 2 or cfg.height % 2:
        raise UsageError(f"--width {cfg.width} --height {cfg.height}: sides must be even (H.264 yuv420p)")
    if not 3 <= cfg.frames <= 20000:
        raise UsageError(f"--frames {cfg.frames}: must be between 3 and 20000 (one loop per ring needs at least 3)")
    if cfg.seed < 0 or cfg.seed >= 2**63:
        raise UsageError(f"--seed {cfg.seed}: must be a non-negative integer below 2^63")
    if not 0 <= cfg.crf <= 51:
        raise UsageError(f"--crf {cfg.crf}: must be between 0 and 51")
    if not 1 <= cfg.msaa <= 16:
        raise UsageError(f"--msaa {cfg.msaa}: must be between 1 and 16")
    if not 0 < cfg.gt_density <= 1000:
        raise UsageError(f"--gt-density {cfg.gt_density}: must be in (0, 1000] samples per cm^2")


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for mod in ("numpy", "moderngl", "cv2", "av"):
        try:
            out[mod] = getattr(importlib.import_module(mod), "__version__", "?")
        except Exception:  # noqa: BLE001 - informational only
            out[mod] = None
    return out


def _preview_tile(rgb: np.ndarray, mask: np.ndarray, markers: list[int], ring: str, width: int = 240) -> np.ndarray:
    """A frame above the same frame with its mask outline, captioned with the ring and visible markers."""
    h = int(round(rgb.shape[0] * width / rgb.shape[1]))
    small = cv2.resize(rgb, (width, h), interpolation=cv2.INTER_AREA)
    m = cv2.resize(mask, (width, h), interpolation=cv2.INTER_NEAREST)
    over = (small * 0.45).astype(np.uint8)
    over[m > 0] = small[m > 0]
    edge = cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    over[edge] = (255, 230, 0)
    cv2.putText(over, f"{ring} ring, markers {markers}", (6, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                cv2.LINE_AA)
    return np.concatenate([small, over], axis=0)


def _remove_stale_frames(out: Path, n: int) -> None:
    """With --force over an earlier synth capture, drop its frames/masks beyond the new frame count.

    Only folders of a previous ``plantsplat synth`` run (its ``ground_truth.json`` has our format) are
    touched, and only ``frame_NNNNN.png`` files with an index >= ``n``.
    """
    try:
        old = json.loads((out / "ground_truth.json").read_text())
    except (OSError, ValueError):
        return
    if not isinstance(old, dict) or old.get("format") != FORMAT:
        return
    for sub in ("frames", "masks", "objects", "classes"):
        for p in (out / sub).glob("frame_*.png"):
            stem = p.stem.split("_")[-1]
            if stem.isdigit() and int(stem) >= n:
                p.unlink()


def write_capture(cfg: SynthConfig) -> dict:
    """Write a complete capture into ``cfg.out`` and return paths, timings and the ground-truth traits."""
    validate(cfg)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    try:
        out = prepare_output_dir(cfg.out, cfg.force)
    except OSError as exc:
        raise UsageError(f"{cfg.out}: cannot create the output folder ({exc.strerror}); choose another --out") from exc
    _remove_stale_frames(out, cfg.frames)
    (out / "frames").mkdir(exist_ok=True)
    (out / "masks").mkdir(exist_ok=True)
    if cfg.object_renders:
        (out / "objects").mkdir(exist_ok=True)
    if cfg.class_maps:
        (out / "classes").mkdir(exist_ok=True)
    s_scene, s_tex, s_cam, s_sensor, s_gt, s_noise = np.random.SeedSequence(cfg.seed).spawn(6)
    cube = CubeSpec()

    t = time.perf_counter()
    log.info("synth seed %d: building the plant, pot, cube and room", cfg.seed)
    scene = make_scene(np.random.default_rng(s_scene), cube, hard=cfg.hard)
    tex_size = 512 if max(cfg.width, cfg.height) > 480 else 256  # small frames: smaller textures, same look
    layers = make_layers(np.random.default_rng(s_tex), size=tex_size, cube=cube)
    timings["scene_s"] = time.perf_counter() - t

    # ground truth
    t = time.perf_counter()
    rng_gt = np.random.default_rng(s_gt)
    plant = gt.sample_surface(scene["plant_meshes"], layers, cfg.gt_density, rng_gt)
    cube_meshes = [m for m in scene["meshes"] if m.cls in CUBE_CLASSES]
    cube_s = gt.cube_samples(cube_meshes, layers, cfg.gt_density, rng_gt)
    n_ripe = sum(bool(f["ripe"]) for f in scene["plant_info"]["fruits"])
    traits = gt.traits(plant["xyz"], n_ripe, soil_z=scene["pot"].soil_z)
    gt.write_ply(out / "plant_gt.ply", plant)
    gt.write_ply(out / "scene_gt.ply", {k: np.concatenate([plant[k], cube_s[k]]) for k in plant})
    timings["ground_truth_s"] = time.perf_counter() - t
    log.info("ground truth: %d plant points, height %.1f cm, widths %.1f x %.1f cm, %d fruits",
             len(plant["xyz"]), traits["height_cm"], traits["width1_cm"], traits["width2_cm"], traits["fruit_count"])

    # camera
    rng_cam = np.random.default_rng(s_cam)
    fov_long = float(rng_cam.uniform(*cam.FOV_LONG_RANGE_DEG))
    intr = cam.intrinsics(cfg.width, cfg.height, fov_long)
    K = cam.K_matrix(intr)
    fov_short = float(np.degrees(2 * np.arctan(0.5 * min(cfg.width, cfg.height) / intr["fx"])))
    T_wc = scene["cube"]["T_world_cube"]
    cube_pts = cube.corners() @ T_wc[:3, :3].T + T_wc[:3, 3]
    reach_plant = float(np.linalg.norm(plant["xyz"][:, :2], axis=1).max())
    reach = max(reach_plant, float(np.linalg.norm(cube_pts[:, :2], axis=1).max()))
    if cfg.hard:  # framed mostly on the plant: the cube leaves the frame at times
        reach = reach_plant + 0.3 * (reach - reach_plant)
    pot = scene["pot"]
    c2ws, rings, path = cam.camera_path(rng_cam, cfg.frames, pot.soil_z, traits["height_extent_cm"], reach, fov_short,
                                        shake=2.0 if cfg.hard else 1.0)

    # render
    sensor = SensorModel.draw(np.random.default_rng(s_sensor), cfg.frames, clean=cfg.clean, hard=cfg.hard)
    t = time.perf_counter()
    renderer = Renderer(scene["meshes"], layers, intr, scene["lights"], samples=cfg.msaa,
                        shadow_radius=scene["platform"]["radius_cm"] + 100.0,
                        shadow_size=4096 if max(cfg.width, cfg.height) > 720 else 2048,
                        object_classes=FOREGROUND_CLASSES if cfg.object_renders else ())
    ideal = SensorModel.draw(np.random.default_rng(0), cfg.frames, clean=True) if cfg.object_renders else None
    timings["gl_setup_s"] = time.perf_counter() - t
    log.info("rendering %d frames at %dx%d (%s)", cfg.frames, cfg.width, cfg.height, renderer.ctx.info["GL_RENDERER"])
    axis_pt = np.array([[0.0, 0.0, pot.soil_z]])
    axis_uv = np.stack([gt.project_to_pixels(K, c, axis_pt)[0] for c in c2ws])  # [n, 2]
    fg = np.zeros(256, bool)
    fg[list(FOREGROUND_CLASSES)] = True
    frames_json = []
    t_render = t_dev = t_vis = 0.0
    video_path = out / "video.mp4"
    fg_frac = []
    preview_idx = set(np.linspace(0, cfg.frames - 1, min(6, cfg.frames)).round().astype(int).tolist())
    previews = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending = []
        for i in progress(range(cfg.frames), "rendering frames"):
            t0 = time.perf_counter()
            linear, ids = renderer.render(c2ws[i])
            t1 = time.perf_counter()
            if i == 0:
                sensor.calibrate(linear)
                if ideal is not None:  # objects/ are developed at the frames' base gain
                    ideal.base_gain = sensor.base_gain
            j0, j1 = max(i - 1, 0), min(i + 1, cfg.frames - 1)
            motion = axis_uv[j1] - axis_uv[j0]
            rgb = sensor.develop(linear, i, np.random.default_rng([s_noise.entropy, i]),
                                 blur_dir=motion if np.linalg.norm(motion) > 1e-6 else (1.0, 0.0))
            mask = np.where(fg[ids], 255, 0).astype(np.uint8)
            t2 = time.perf_counter()
            visible = gt.markers_visible(ids, c2ws[i], K, scene["cube"]["markers"], cube, T_wc)
            t3 = time.perf_counter()
            name = IMAGE_PATTERN.format(i)
            pending.append(pool.submit(write_image_atomic, out / "frames" / name, rgb))
            pending.append(pool.submit(write_image_atomic, out / "masks" / name, mask))
            if cfg.class_maps:
                pending.append(pool.submit(write_image_atomic, out / "classes" / name, ids))
            if ideal is not None:
                obj = ideal.develop(renderer.render_objects(c2ws[i]), i, np.random.default_rng(0))
                pending.append(pool.submit(write_image_atomic, out / "objects" / name, obj))
            t_render += t1 - t0
            t_dev += t2 - t1
            t_vis += t3 - t2
            fg_frac.append(float(mask.mean() / 255))
            if i in preview_idx:
                previews.append(_preview_tile(rgb, mask, visible, rings[i]))
            frames_json.append(dict(index=i, file=f"frames/{name}", mask=f"masks/{name}",
                                    **({"object": f"objects/{name}"} if cfg.object_renders else {}),
                                    **({"classes": f"classes/{name}"} if cfg.class_maps else {}),
                                    time_s=i / FPS, ring=rings[i],
                                    c2w=c2ws[i], cube_markers_visible=visible,
                                    motion_blur_px=float(sensor.blur_px[i]),
                                    exposure_ev=float(sensor.exposure_ev[i]),
                                    plant_or_cube_fraction=fg_frac[-1]))
            if len(pending) > 16:
                for f in pending[:-8]:
                    f.result()
                pending = pending[-8:]
        for f in pending:
            f.result()
    video_settings = encode_frames([out / "frames" / IMAGE_PATTERN.format(i) for i in range(cfg.frames)], video_path,
                                   cfg.width, cfg.height, FPS, cfg.crf)  # the same frames, the same video
    write_image_atomic(out / "preview.png", np.concatenate(previews, axis=1))
    gl_renderer = renderer.ctx.info["GL_RENDERER"]
    renderer.release()
    timings.update(render_s=t_render, develop_s=t_dev, visibility_s=t_vis)

    cube_info = dict(size_cm=cube.size, marker_size_cm=cube.marker_size, dictionary=cube.dictionary,
                     face_ids=list(cube.face_ids), face_names=["+x", "-x", "+y", "-y", "top", "bottom"],
                     T_world_cube=T_wc, markers=scene["cube"]["markers"],
                     azimuth_deg=scene["cube"]["azimuth_deg"], distance_from_pot_axis_cm=scene["cube"]["distance_cm"])
    info = scene["plant_info"]
    plant_json = dict(n_leaves=info["n_leaves"], n_fruits=info["n_fruits"], n_flowers=info["n_flowers"],
                      soil_z_cm=pot.soil_z, pot=pot.as_dict(), crown_xyz_cm=info["crown_xyz"],
                      crown_radius_cm=info["crown_radius_cm"], size_scale=info["size_scale"],
                      anisotropy=info["anisotropy"], leaves=info["leaves"], fruits=info["fruits"],
                      flowers=info["flowers"], n_gt_points=int(len(plant["xyz"])),
                      organ_codes={"1": "leaf", "2": "petiole", "3": "crown", "4": "fruit (with calyx)",
                                   "5": "peduncle", "6": "flower", "10": "cube"})
    timings["total_s"] = time.perf_counter() - t_all
    doc = dict(
        format=FORMAT, seed=int(cfg.seed), hard=bool(cfg.hard), units="cm", world_frame=WORLD_FRAME,
        **{k: traits[k] for k in TRAIT_KEYS},
        fruit_count_all=int(scene["plant_info"]["n_fruits"]),
        trait_source="plant_gt.ply (all plant mesh vertices + area-uniform samples), plantsplat.traitdefs",
        plant=plant_json, platform=scene["platform"], room=scene["room"], lights=scene["lights"],
        intrinsics=intr, pixel_convention=PIXEL_CONVENTION, camera_convention=CAMERA_CONVENTION,
        camera_path=dict(path, fov_long_side_deg=fov_long, rings_above_soil_cm=cam.RINGS),
        frames=frames_json, cube=cube_info, fps=FPS,
        render=dict(renderer=f"moderngl {gl_renderer} (EGL)", msaa_samples=int(cfg.msaa), mask_rule=MASK_RULE,
                    clean=bool(cfg.clean), sensor=sensor.settings(), video=video_settings,
                    **({"objects": OBJECTS_RULE} if cfg.object_renders else {}),
                    **({"classes": CLASSES_RULE} if cfg.class_maps else {}),
                    texture_layer_size=int(layers.shape[1])),
        versions=_versions(),
        timings_s=timings,
    )
    write_json_atomic(out / "ground_truth.json", doc)
    log.info("wrote %s in %.1f s (render %.1f s)", out, timings["total_s"], t_render)
    return dict(out=out, paths=dict(video=video_path, frames=out / "frames", masks=out / "masks",
                                    plant_gt=out / "plant_gt.ply", scene_gt=out / "scene_gt.ply",
                                    ground_truth=out / "ground_truth.json", preview=out / "preview.png",
                                    **({"objects": out / "objects"} if cfg.object_renders else {}),
                                    **({"classes": out / "classes"} if cfg.class_maps else {})),
                timings=timings, traits=traits, frames=cfg.frames)

