"""Benchmark of `plantsplat report` on a 50k-Gaussian plant: build time, file size, open time and orbit
frame rate in headless Chromium (file://, WebGL on SwiftShader, i.e. on the CPU).

Targets: the report opens in under 3 s, orbits smoothly, and stays under 20 MB.
"Open time" is navigation start -> first frame with the splat drawn (measured in the page), the
median of ``--opens`` fresh page loads. The orbit turns the camera a full circle in ``--orbit-frames``
displayed frames with the viewer's defaults (after a 10-frame orbit during which it adapts: lower
resolution, then a level-of-detail preview of the most visible Gaussians, only while moving and only
when frames are slow), and then with the full model at full resolution.
SwiftShader renders WebGL on the CPU, so frame rates here are a floor far below any laptop GPU, and
they depend on the machine's load (recorded before and after).

Usage::

    .venv/bin/python benchmarks/bench_report.py            # -> benchmarks/results/report.json
    .venv/bin/python benchmarks/bench_report.py --gaussians 50000 --opens 3 --orbit-frames 30
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))


def machine_info() -> dict:
    from plantsplat.report.browser import find_chromium
    from plantsplat.resources import machine_info as common

    exe = find_chromium()
    chromium = ""
    if exe:
        try:
            chromium = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            chromium = exe
    try:
        from importlib.metadata import version

        pw = version("playwright")
    except Exception:  # noqa: BLE001 - informational
        pw = None
    vendored = (ROOT / "src/plantsplat/report/assets/VENDORED.md").read_text().splitlines()
    libs = [ln.strip("| ").split(" | ")[:2] for ln in vendored if ln.startswith("| ") and "---" not in ln][1:]
    return {**common(), "chromium": chromium, "playwright": pw,
            "viewer_libraries": {a: b for a, b in libs}, "webgl": "SwiftShader (CPU)"}


def main(argv=None) -> int:
    os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")
    from plantsplat.io import write_json_atomic
    from plantsplat.report.browser import (
        ReportBrowser,
        find_chromium,
        playwright_available,
    )
    from plantsplat.report.plant import write_report
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the tests' synthetic workspaces
    from report_workspace import make_synthetic_workspace

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--opens", type=int, default=3)
    ap.add_argument("--orbit-frames", type=int, default=30)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "report.json")
    ap.add_argument("--screenshot", type=Path, default=None, help="save a full-page screenshot of the report here")
    args = ap.parse_args(argv)
    if find_chromium() is None or not playwright_available():
        print("needs chromium (apt-get install chromium) and playwright (pip install playwright)", file=sys.stderr)
        return 2

    result: dict = {"machine": machine_info(), "loadavg_before": os.getloadavg(), "gaussians": args.gaussians}
    with tempfile.TemporaryDirectory() as tmp:
        ws = make_synthetic_workspace(Path(tmp) / "plant", n_gaussians=args.gaussians, n_frames=24,
                                      image_size=(480, 360))
        t0 = time.perf_counter()
        report = write_report(ws)
        result["build_s"] = round(time.perf_counter() - t0, 2)
        size = report.stat().st_size
        result["size_mb"] = round(size / 1e6, 2)
        result["splat_mb_base64"] = round(args.gaussians * 32 * 4 / 3 / 1e6, 2)
        opens, loads, errors = [], [], []
        with ReportBrowser(viewport=(1280, 900)) as browser:
            for i in range(args.opens):
                last = i == args.opens - 1
                res = browser.open(report, timeout_s=120, orbit_frames=10 if last else 0,
                                   keep_page=last,
                                   screenshot=args.screenshot if last else None)
                if res.viewer_state != "ready":
                    raise SystemExit(f"viewer did not get ready: {res.viewer_state} {res.viewer_error}")
                opens.append(res.first_content_s)
                loads.append(res.load_s)
                errors += res.console_errors
            # the first orbit lets the viewer adapt (resolution, preview, level of detail); then measure
            result["orbit_adapting"] = res.orbit
            page = res.page
            result["orbit_adaptive"] = page.evaluate(f"window.plantsplatViewer.orbit({args.orbit_frames})")
            # and right after it, with no pause: sustained orbiting (no switch back to the full model)
            result["orbit_adaptive_sustained"] = page.evaluate(f"window.plantsplatViewer.orbit({args.orbit_frames})")
            page.evaluate("window.plantsplatViewer.setAdaptive(false)")
            result["orbit_full_model_full_resolution"] = page.evaluate(
                f"window.plantsplatViewer.orbit({max(4, args.orbit_frames // 5)})")
            result["canvas_px"] = page.evaluate("[document.getElementById('viewer-canvas').width, "
                                                "document.getElementById('viewer-canvas').height]")
            page.close()
        result["open_s_runs"] = [round(x, 3) for x in opens]
        result["open_s_median"] = round(statistics.median(opens), 3)
        result["load_event_s_median"] = round(statistics.median(loads), 3)
        result["console_errors"] = errors
    result["loadavg_after"] = os.getloadavg()
    o, sus = result["orbit_adaptive"], result["orbit_adaptive_sustained"]
    result["targets"] = {
        "size_mb < 20": result["size_mb"] < 20,
        "open_s < 3": result["open_s_median"] < 3,
        "orbit median fps >= 20 (adaptive viewer)": o["medianFps"] >= 20,
        "orbit mean fps >= 20 (adaptive viewer, sustained)": sus["fps"] >= 20,
    }
    write_json_atomic(args.out, result)
    print(f"report {result['size_mb']} MB built in {result['build_s']} s; open {result['open_s_median']} s "
          f"(runs {result['open_s_runs']}); orbit (adaptive) median {o['medianFps']:.1f} fps, mean {o['fps']:.1f} fps, "
          f"worst frame {o['maxMsPerFrame']:.0f} ms; sustained mean {sus['fps']:.1f} fps (pixel ratio "
          f"{sus['pixelRatio']:.2f}, preview splats {sus['preview']}); full model at full resolution median "
          f"{result['orbit_full_model_full_resolution']['medianFps']:.2f} fps; load {result['loadavg_before']} -> "
          f"{result['loadavg_after']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
