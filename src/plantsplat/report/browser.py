"""Open a report in headless Chromium and check what a reader would see (used by tests and benchmarks).

Drives the system's Chromium (Debian package ``chromium``) through Playwright's Python API; no browser
download. WebGL runs on the CPU through SwiftShader.

Usage:
    from plantsplat.report.browser import find_chromium, open_report
    if find_chromium():
        res = open_report("ws/report.html", screenshot="shot.png")
        res.viewer_state, res.console_errors
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

CHROMIUM_ARGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-dev-shm-usage",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
]


def find_chromium() -> str | None:
    """Path of a Chromium binary (``$PLANTSPLAT_CHROMIUM``, ``chromium``, ``chromium-browser``), or None."""
    env = os.environ.get("PLANTSPLAT_CHROMIUM")
    if env and Path(env).is_file():
        return env
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def playwright_available() -> bool:
    try:
        import playwright.sync_api  # noqa: F401  (deferred: Playwright is optional, a test dependency)
    except ImportError:
        return False
    return True


@dataclass
class BrowserResult:
    """What :func:`open_report` saw."""

    load_s: float  # navigation start -> load event
    viewer_state: str | None  # 'ready' / 'error' / 'loading' (timed out) / None (no viewer on the page)
    viewer_error: str | None
    first_content_s: float | None  # navigation start -> first viewer frame with drawn pixels
    canvas_fraction: float | None  # share of canvas pixels that differ from the background (screenshot)
    console_errors: list[str] = field(default_factory=list)
    orbit: dict | None = None  # {'fps', 'msPerFrame', 'frames'}
    mode_fractions: dict[str, float] = field(default_factory=dict)
    screenshot: Path | None = None
    canvas_image: np.ndarray | None = None  # [H, W, 3] uint8 of the viewer canvas


def _drawn_fraction(img: np.ndarray, background: tuple[int, int, int]) -> float:
    diff = np.abs(img[..., :3].astype(np.int32) - np.array(background)).sum(-1)  # [H, W]
    return float((diff > 60).mean())


def _decode_png(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class ReportBrowser:
    """One headless Chromium for several reports (launching takes about a second).

    Usage:
        with ReportBrowser() as b:
            r1 = b.open("a/report.html")
            r2 = b.open("b/report.html", screenshot="b.png")
    """

    def __init__(self, viewport: tuple[int, int] = (1280, 900), extra_args: tuple[str, ...] = ()):
        self.viewport = viewport
        self.extra_args = list(extra_args)
        self._pw = None
        self.browser = None

    def __enter__(self) -> "ReportBrowser":
        from playwright.sync_api import sync_playwright  # deferred: Playwright is optional, a test dependency

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("chromium not found; install the Debian package `chromium`")
        self._pw = sync_playwright().start()
        try:
            self.browser = self._pw.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS + self.extra_args,
                                                    headless=True)
        except BaseException:
            self._pw.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        try:
            if self.browser is not None:
                self.browser.close()
        finally:
            self._pw.stop()

    def new_page(self, errors: list[str]):
        """A fresh page that appends console errors, page errors and failed requests to ``errors``."""
        page = self.browser.new_page(viewport={"width": self.viewport[0], "height": self.viewport[1]})
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(f"pageerror: {e}"))
        page.on("requestfailed", lambda r: errors.append(f"requestfailed: {r.url[:120]}"))
        return page

    def open(
        self,
        path: str | os.PathLike,
        screenshot: str | os.PathLike | None = None,
        timeout_s: float = 60.0,
        orbit_frames: int = 0,
        modes: tuple[str, ...] = (),
        background: tuple[int, int, int] = (0x20, 0x21, 0x24),
        keep_page: bool = False,
    ) -> BrowserResult:
        """Open ``path`` from ``file://`` and wait for the viewer (if any) to draw; see :func:`open_report`."""
        errors: list[str] = []
        page = self.new_page(errors)
        try:
            t0 = time.perf_counter()
            page.goto(Path(path).resolve().as_uri(), wait_until="load", timeout=timeout_s * 1000)
            load_s = page.evaluate("performance.getEntriesByType('navigation')[0].loadEventEnd / 1000")
            has_viewer = page.evaluate("!!window.plantsplatViewer && !!document.getElementById('viewer-canvas')")
            state = err = first = frac = orbit = canvas_img = None
            mode_fracs: dict[str, float] = {}
            if has_viewer:
                deadline = t0 + timeout_s
                while time.perf_counter() < deadline:
                    st = page.evaluate("[window.plantsplatViewer.state, window.plantsplatViewer.firstContentMs]")
                    if st[0] == "error" or (st[0] == "ready" and st[1] is not None):
                        break
                    page.wait_for_timeout(50)
                state, err, first_ms = page.evaluate(
                    "[window.plantsplatViewer.state, window.plantsplatViewer.error, window.plantsplatViewer.firstContentMs]")
                first = None if first_ms is None else first_ms / 1000.0
                canvas = page.locator("#viewer-canvas")
                canvas.scroll_into_view_if_needed()
                canvas_img = _decode_png(canvas.screenshot())
                frac = _drawn_fraction(canvas_img, background)
                for mode in modes:
                    page.evaluate(f"window.plantsplatViewer.setMode({mode!r})")
                    page.evaluate("window.plantsplatViewer.rendered()")
                    mode_fracs[mode] = _drawn_fraction(_decode_png(canvas.screenshot()), background)
                if orbit_frames > 0 and state == "ready":
                    orbit = page.evaluate(f"window.plantsplatViewer.orbit({int(orbit_frames)})")
            shot = None
            if screenshot is not None:
                shot = Path(screenshot)
                shot.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(shot), full_page=True)
        finally:
            if not keep_page:
                page.close()
        res = BrowserResult(load_s=load_s, viewer_state=state, viewer_error=err, first_content_s=first,
                            canvas_fraction=frac, console_errors=errors, orbit=orbit, mode_fractions=mode_fracs,
                            screenshot=shot, canvas_image=canvas_img)
        if keep_page:
            res.page = page  # type: ignore[attr-defined]
        return res


def open_report(path: str | os.PathLike, screenshot: str | os.PathLike | None = None, timeout_s: float = 60.0,
                orbit_frames: int = 0, modes: tuple[str, ...] = (), viewport: tuple[int, int] = (1280, 900)) -> BrowserResult:
    """Open ``path`` from ``file://`` in a new headless Chromium and wait for the viewer (if any) to draw.

    ``orbit_frames`` > 0 turns the camera a full circle in that many frames and reports the frame rate;
    ``modes`` (e.g. ``("points", "splat")``) switches the viewer to each mode and measures drawn pixels.
    """
    with ReportBrowser(viewport) as b:
        return b.open(path, screenshot=screenshot, timeout_s=timeout_s, orbit_frames=orbit_frames, modes=modes)
