"""Drive ``autoalign label`` as a person would, for its tests and its benchmark: the server in a
child process, the page in a real headless Chromium (Playwright pointed at Debian's ``chromium``:
Playwright's own browser download cannot be reached from these machines).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from autoalign.experiments.commands import autoalign_command

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
STARTUP_S = 120.0


def chromium_path() -> str:
    """Debian's Chromium (``AUTOALIGN_CHROMIUM`` overrides); raises if none is installed."""
    given = os.environ.get("AUTOALIGN_CHROMIUM")
    found = given or next((p for n in CHROMIUM_NAMES if (p := shutil.which(n))), None)
    if not found:
        raise RuntimeError("no Chromium found: install Debian's chromium package (.ci/install does)")
    return found


def launch_browser(playwright: Any) -> Any:
    """A headless Chromium from ``playwright.sync_api.sync_playwright()``."""
    return playwright.chromium.launch(executable_path=chromium_path(), headless=True,
                                      args=["--no-sandbox", "--disable-gpu"])


@dataclass
class LabelServerProcess:
    """``autoalign label SCENE --models MODELS --out OUT --no-browser`` in a child process.

    ``url`` is the page's address, read from the line the command prints when it is ready. With
    ``cwd`` (a checkout of other code) the server is that checkout's, with its page.
    """

    scene: Path
    models: Path
    out: Path
    extra: tuple[str, ...] = ()
    proc: subprocess.Popen | None = None
    url: str = ""
    output: str = ""
    cwd: Path | None = None

    def start(self) -> "LabelServerProcess":
        cmd = autoalign_command("label", str(self.scene), "--models", str(self.models), "--out", str(self.out),
                                "--no-browser", *self.extra)
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=self.cwd)
        t0 = time.monotonic()
        lines = []
        assert self.proc.stdout is not None
        while time.monotonic() - t0 < STARTUP_S:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError("autoalign label stopped before it was ready:\n" + "".join(lines))
            lines.append(line)
            m = re.search(r"autoalign label: (http://127\.0\.0\.1:\d+/)", line)
            if m:
                self.url = m.group(1)
                self.output = "".join(lines)
                return self
        raise RuntimeError("autoalign label did not start in time:\n" + "".join(lines))

    @property
    def port(self) -> int:
        return int(self.url.rstrip("/").rsplit(":", 1)[1])

    def stop(self, sig: int = signal.SIGINT) -> int:
        """Stop the server (Ctrl-C by default, ``SIGKILL`` to pull the plug); its exit status."""
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        if self.proc.stdout is not None:
            self.output += self.proc.stdout.read()
        return rc

    def __enter__(self) -> "LabelServerProcess":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.stop(signal.SIGKILL)


def open_page(browser: Any, url: str, n_views: int) -> Any:
    """A new tab on the page, once every view and instance is shown."""
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    page.goto(url)
    page.wait_for_function(f"document.querySelectorAll('.view').length === {n_views} && "
                           "document.querySelectorAll('.instance').length > 0 && "
                           "[...document.querySelectorAll('.view img')].every(i => i.complete && i.naturalWidth > 0)")
    return page


def mask_pixel(mask: np.ndarray) -> tuple[int, int]:
    """A pixel (column, row) well inside ``mask``: its farthest from the mask's border."""
    import cv2

    dist = cv2.distanceTransform(np.pad(mask.astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    row, col = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(col), int(row)


def click_view(page: Any, image_id: int, col: int, row: int, width: int, height: int) -> None:
    """Click pixel (``col``, ``row``) (OpenCV: its centre) of view ``image_id`` on the page."""
    tint = page.locator(f'.view[data-image-id="{image_id}"] img.tint')
    tint.scroll_into_view_if_needed()
    box = tint.bounding_box()
    page.mouse.click(box["x"] + (col + 0.5) * box["width"] / width, box["y"] + (row + 0.5) * box["height"] / height)


def wait_drawn(page: Any, instance: int, after_revision: int = 0, timeout_s: float = 60.0) -> int:
    """Wait until the page drew instance ``instance``'s outlines at a pose revision above
    ``after_revision``; that revision."""
    page.wait_for_function(
        f"(() => {{ const m = (document.body.dataset.drawn || '').match(/(^|,){instance}:(\\d+)/); "
        f"return m && +m[2] > {after_revision}; }})()", timeout=timeout_s * 1000)
    m = re.search(rf"(^|,){instance}:(\d+)", page.evaluate("document.body.dataset.drawn"))
    assert m is not None
    return int(m.group(2))


def wait_state(page: Any, predicate: str, timeout_s: float = 60.0) -> dict:
    """The session's state (``GET /api/state``) once the JavaScript expression ``predicate`` of it
    (``s``) is true. Polled from here: ``page.wait_for_function`` takes a promise for a true value."""
    end = time.monotonic() + timeout_s
    while True:
        met, state = page.evaluate(f"fetch('/api/state').then(r => r.json()).then(s => [!!({predicate}), s])")
        if met:
            return state
        if time.monotonic() > end:
            raise TimeoutError(f"the label server's state did not come to {predicate} in {timeout_s:g} s: {state['job']}")
        time.sleep(0.2)


def wait_job_done(page: Any, number: int | None = None, timeout_s: float = 120.0) -> dict:
    """The session's state once its job (number ``number``, default the latest) has finished."""
    return wait_state(page, "!s.job.running" + (f" && s.job.number >= {number}" if number is not None else ""),
                      timeout_s)


@dataclass
class Placement:
    """One click of :func:`place_in_largest_view`: the view clicked, the times from the click to the
    judged pose's outlines on screen, to the first outlines (the orientation search's pose, dashed)
    and to the first refined pose's (before its uncertainty and verdict; s, measured in the page),
    and the session's state once the job ended."""

    image_id: int
    click_to_outlines_s: float
    state: dict
    click_to_first_outlines_s: float | None  # None: the page draws no outline before the judged pose
    click_to_refined_pose_s: float | None = None  # None: the page draws no refined pose before the judged one

    def instance(self, index: int) -> dict:
        return next(i for i in self.state["instances"] if i["index"] == index)


def place_in_largest_view(page: Any, scene: Path, index: int, obj_id: int) -> Placement:
    """Choose ``obj_id`` and click instance ``index`` in the view where its mask is largest (a pixel
    well inside it); wait for its outlines and for the job to end."""
    import cv2

    state = page.evaluate("fetch('/api/state').then(r => r.json())")
    sizes = {v["image_id"]: (v["width"], v["height"]) for v in state["views"]}
    views = [(im, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0) for im in sizes
             if (p := scene / "mask_visib" / f"{im:06d}_{index:06d}.png").is_file()]
    im, mask = max(views, key=lambda v: int(v[1].sum()))
    w, h = sizes[im]  # the masks may have been downscaled on reading: click in the views' resolution
    mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    page.select_option("#object", str(obj_id))
    page.evaluate("delete document.body.dataset.clickToContoursMs; "
                  "delete document.body.dataset.clickToFirstOutlinesMs; "
                  "delete document.body.dataset.clickToRefinedPoseMs")
    col, row = mask_pixel(mask)
    click_view(page, im, col, row, w, h)
    try:
        wait_drawn(page, index)
    except Exception:
        raise RuntimeError(f"instance {index}: no outlines; the page says {page.inner_text('#status')!r}") from None
    page.wait_for_function("document.body.dataset.clickToContoursMs !== undefined")
    ms = float(page.evaluate("document.body.dataset.clickToContoursMs"))
    first_ms = page.evaluate("document.body.dataset.clickToFirstOutlinesMs")  # set first, by pages that draw it
    refined_ms = page.evaluate("document.body.dataset.clickToRefinedPoseMs")  # likewise
    return Placement(im, ms / 1000.0, wait_job_done(page), None if first_ms is None else float(first_ms) / 1000.0,
                     None if refined_ms is None else float(refined_ms) / 1000.0)
