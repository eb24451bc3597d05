"""Frame time of the ground station page in headless Chromium (``swarm bench gcs``).

The page is opened in Debian's chromium driven by Playwright (no browser download:
``executable_path`` points at the system browser). Once state snapshots stream in,
the page's own probe (``window.gcs.frameProbe``) records requestAnimationFrame
deltas for ``seconds``; their percentiles are the page's frame time: a frame that
took long to draw, or a main thread blocked by parsing and drawing a snapshot,
shows as a long delta.
"""

from __future__ import annotations

import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from swarm.errors import SwarmError

#: where Debian (chromium) and other distributions (chromium-browser) put it
BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome")

#: headless flags for a machine with no network beyond loopback: no background
#: connections, no component updates, no first-run work (as root: no sandbox)
BROWSER_ARGS = (
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--mute-audio",
)


class BrowserError(SwarmError):
    """No headless browser (or no Playwright) to open the page with."""


def find_browser() -> str | None:
    """The system Chromium: ``$CHROMIUM`` if set, else the first on PATH."""
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for name in BROWSER_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


@contextmanager
def launch_browser(*, width: int = 1400, height: int = 900) -> Iterator[Any]:
    """A Playwright browser context on the system Chromium (headless), closed on exit.

    Raises:
        BrowserError: no Chromium found, or Playwright for Python not installed
            (``make setup`` installs both).
    """
    path = find_browser()
    if path is None:
        raise BrowserError("no chromium found (make setup installs Debian's chromium; or set CHROMIUM)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:  # the test extra
        raise BrowserError("Playwright for Python is not installed (make setup installs it)") from exc
    with tempfile.TemporaryDirectory(prefix="gcs-browser-") as profile, sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            profile,
            executable_path=path,
            headless=True,
            args=list(BROWSER_ARGS),
            viewport={"width": width, "height": height},
        )
        try:
            yield ctx
        finally:
            ctx.close()


def percentile(values: list[float], q: float) -> float:
    """The ``q``-quantile (0..1) by linear interpolation; 0.0 for no values."""
    if not values:
        return 0.0
    xs = sorted(values)
    k = (len(xs) - 1) * q
    lo = int(k)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


#: collects the browser's long animation frames (its own timeline: frames whose work took
#: over 50 ms, script and rendering) into ``window.__loaf`` (their durations, ms)
LOAF_OBSERVER = """() => {
  window.__loaf = [];
  try {
    new PerformanceObserver((list) => { for (const e of list.getEntries()) window.__loaf.push(e.duration); })
      .observe({ type: "long-animation-frame" });
  } catch (err) { /* a browser without it: none counted */ }
}"""


def _metrics(cdp: Any) -> dict[str, float]:
    """Chromium's own counters (CDP Performance.getMetrics): seconds of task, script,
    layout and style work on the page's main thread since it opened."""
    got = cdp.send("Performance.getMetrics")["metrics"]
    return {m["name"]: float(m["value"]) for m in got}


def measure_frames(url: str, seconds: float, *, ready_timeout: float = 30.0) -> dict[str, Any]:
    """Open the page at ``url`` headless and measure its frame time for ``seconds``.

    Waits until the page has drawn at least one state snapshot (markers on the
    map), then records requestAnimationFrame deltas while updates stream in.

    Returns:
        ``page_frame_ms_p50``, ``page_frame_ms_p95``, ``page_frame_ms_p99``,
        ``page_frame_ms_max``, ``frames``, ``long_frames`` (deltas over 50 ms),
        ``render_ms_p50`` and ``render_ms_p95`` (time the page spent drawing one snapshot),
        ``states`` (snapshots received while measuring), from the browser's own timeline
        ``page_main_thread_busy_percent`` (its main thread's task time over the window),
        ``page_script_ms_per_s`` and ``page_layout_style_ms_per_s``, and
        ``page_long_animation_frames`` (frames whose work took over 50 ms, as Chromium
        reports them) with the longest; ``markers`` and ``seconds``.

    Raises:
        BrowserError: no browser, or the page drew no state within ``ready_timeout``.
    """
    with launch_browser() as ctx:
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url)
        try:
            page.wait_for_function(
                "() => window.gcs && window.gcs.ready && window.gcs.markers > 0", timeout=ready_timeout * 1000
            )
        except Exception as exc:
            raise BrowserError(
                f"the page at {url} drew no agent in {ready_timeout:.0f} s: {exc}; page errors: {errors[-3:]}"
            ) from exc
        states0 = page.evaluate("window.gcs.stateCount")
        # the browser's own timeline: its main thread's task time (CDP Performance) and the
        # long animation frames it reports (work over 50 ms in one frame: PerformanceObserver)
        cdp = ctx.new_cdp_session(page)
        cdp.send("Performance.enable")
        page.evaluate(LOAF_OBSERVER)
        m0, w0 = _metrics(cdp), time.monotonic()
        page.evaluate("window.gcs.frameProbe.start()")
        time.sleep(seconds)
        deltas: list[float] = page.evaluate("window.gcs.frameProbe.stop()")
        m1, w1 = _metrics(cdp), time.monotonic()
        loafs: list[float] = page.evaluate("window.__loaf.splice(0)")
        wall = max(1e-6, w1 - w0)
        renders: list[float] = page.evaluate("window.gcs.renderTimes()")
        states1 = page.evaluate("window.gcs.stateCount")
        markers = page.evaluate("window.gcs.markers")
    return {
        "page_frame_ms_p50": round(percentile(deltas, 0.50), 2),
        "page_frame_ms_p95": round(percentile(deltas, 0.95), 2),
        "page_frame_ms_p99": round(percentile(deltas, 0.99), 2),
        "page_frame_ms_max": round(max(deltas), 2) if deltas else 0.0,
        "page_frame_ms_mean": round(statistics.fmean(deltas), 2) if deltas else 0.0,
        "frames": len(deltas),
        "long_frames": sum(1 for d in deltas if d > 50.0),
        "render_ms_p50": round(percentile(renders, 0.50), 2),
        "render_ms_p95": round(percentile(renders, 0.95), 2),
        "states": states1 - states0,
        "page_main_thread_busy_percent": round(100.0 * (m1["TaskDuration"] - m0["TaskDuration"]) / wall, 1),
        "page_script_ms_per_s": round(1000.0 * (m1["ScriptDuration"] - m0["ScriptDuration"]) / wall, 1),
        "page_layout_style_ms_per_s": round(
            1000.0 * sum(m1[k] - m0[k] for k in ("LayoutDuration", "RecalcStyleDuration")) / wall, 1
        ),
        "page_long_animation_frames": len(loafs),
        "page_long_animation_frame_ms_max": round(max(loafs), 1) if loafs else 0.0,
        "markers": markers,
        "seconds": seconds,
        "page_errors": errors,
    }
