"""The recording opened in the Rerun web viewer in headless Chromium: every view draws its content.

Needs Debian's ``chromium`` and a private network namespace (``unshare -n``, root); skips with the
reason otherwise. ``WINDOWVO_UPDATE_DOCS=1`` also copies the light-theme screenshot to
``docs/viewer.png`` (the README's picture is made this way from the default run).
"""

from __future__ import annotations

import itertools
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import make_config

from windowvo.runtime.job import run_job
from windowvo.viz import rerun_logger as rl
from windowvo.viz.webshot import find_chromium, namespace_problem, screenshot

SIZE = (1920, 1080)
TOP_BAR_PX, TIME_PANEL_PX, TITLE_PX = 40, 36, 30  # viewer chrome at this size (measured on a screenshot)


def _skip_reason() -> str | None:
    if find_chromium() is None:
        return "Chromium is not installed (Debian: apt-get install chromium)"
    return namespace_problem()


def _cells() -> dict[str, tuple[float, float, float, float]]:
    """Each view's cell in the viewport as (x0, y0, x1, y1) fractions, from the blueprint's shares."""
    cols = np.cumsum([0, 3.2, 2.6, 2.1, 2.1]) / 10.0
    def rows(shares):
        edges = np.cumsum([0, *shares]) / sum(shares)
        return list(itertools.pairwise(edges))
    c = {}
    for name, (y0, y1) in zip(["3d", "log"], rows([3, 1.2])):
        c[name] = (cols[0], y0, cols[1], y1)
    for name, (y0, y1) in zip(["camera", "legend"], rows([1, 1.3])):
        c[name] = (cols[1], y0, cols[2], y1)
    for name, (y0, y1) in zip(["counts", "ms"], rows([1, 1])):
        c[name] = (cols[2], y0, cols[3], y1)
    for name, (y0, y1) in zip(["px", "ratios", "states"], rows([1, 1, 0.8])):
        c[name] = (cols[3], y0, cols[4], y1)
    return c


def _region(img: np.ndarray, cell, inset: float = 0.08, top: float = 0.0, bottom: float = 1.0) -> np.ndarray:
    """Pixels (RGB) inside a view: below its title bar, an inset away from its borders; ``top``/``bottom``
    select a vertical band of that inner area."""
    h, w = img.shape[:2]
    vx0, vy0, vx1, vy1 = 0, TOP_BAR_PX, w, h - TIME_PANEL_PX
    x0, y0, x1, y1 = cell
    X0, X1 = vx0 + x0 * (vx1 - vx0), vx0 + x1 * (vx1 - vx0)
    Y0, Y1 = vy0 + y0 * (vy1 - vy0) + TITLE_PX, vy0 + y1 * (vy1 - vy0)
    dx, dy = inset * (X1 - X0), inset * (Y1 - Y0)
    X0, X1, Y0, Y1 = X0 + dx, X1 - dx, Y0 + dy, Y1 - dy
    Y0, Y1 = Y0 + top * (Y1 - Y0), Y0 + bottom * (Y1 - Y0)
    return img[int(Y0):int(Y1), int(X0):int(X1)]


def _near(region: np.ndarray, rgb, tol: float = 45.0) -> int:
    """Pixels within ``tol`` (RGB distance) of a colour."""
    d = np.linalg.norm(region.astype(float) - np.asarray(rgb, float), axis=2)
    return int(np.count_nonzero(d < tol))


def _ink(region: np.ndarray) -> int:
    """Pixels that stand out from the region's background (text, lines, dots)."""
    grey = region.astype(float).mean(axis=2)
    return int(np.count_nonzero(np.abs(grey - np.median(grey)) > 60))


@pytest.fixture(scope="module")
def shots(short_loop, tmp_path_factory):
    reason = _skip_reason()
    if reason is not None:
        pytest.skip(f"web viewer test skipped: {reason}")
    out = tmp_path_factory.mktemp("rerun_web")
    cfg = make_config(short_loop, out / "run", viz={"rerun": "save"}, max_frames=80)
    run_job(cfg)
    paths = screenshot(out / "run" / "recording.rrd", out / "shots", themes=("light", "dark"), size=SIZE,
                       timeout_s=100.0, min_wait_s=6.0)
    if os.environ.get("WINDOWVO_UPDATE_DOCS"):
        shutil.copy(paths[0], Path(__file__).resolve().parents[1] / "docs" / "viewer.png")
    imgs = {}
    for theme, p in zip(("light", "dark"), paths):
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        assert bgr is not None and bgr.shape[:2] == (SIZE[1], SIZE[0]), p
        imgs[theme] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return imgs


@pytest.mark.slow  # a recorded run and a headless browser's screenshots (about 35 s)
@pytest.mark.parametrize("theme", ["light", "dark"])
def test_every_view_draws_its_content(shots, theme):
    img = shots[theme]
    cells = _cells()
    # Not the loading screen (one dark colour with a logo): the page has many distinct colours.
    assert len(np.unique(img.reshape(-1, 3)[::7], axis=0)) > 500
    # 3D: the final trajectory, the keyframes and the window, in their colours, and the landmarks.
    r3d = _region(img, cells["3d"])
    assert _near(r3d, rl.FINAL_RGB) > 40, "final trajectory not drawn"
    assert _near(r3d, rl.ESTIMATE_RGB) > 40, "causal estimate not drawn"
    assert _near(r3d, rl.KEYFRAME_RGB) + _near(r3d, rl.WINDOW_RGB) > 40, "keyframes/window not drawn"
    assert _near(r3d, rl.LANDMARK_RGB, tol=30) > 20, "landmarks not visible"
    # camera: the image (grey texture) under the tracks and their tails
    cam = _region(img, cells["camera"])
    grey = cam.astype(float).mean(axis=2)
    assert np.std(grey) > 20, "camera image not drawn"
    assert _near(cam, rl.TAIL_RGB) > 50, "track tails not drawn"
    # plots: each series' colour below the legend's band (so it is data, not the legend's dot)
    for unit in ("counts", "ms", "px", "ratios"):
        band = _region(img, cells[unit], top=rl.LEGEND_ROWS_SHARE - 0.03)
        _title, series = rl.PLOT_UNITS[unit]
        drawn = [s.label for s in series if _near(band, s.color, tol=50) > 15]
        assert len(drawn) >= 2, (unit, drawn)
    # gate outcomes: lanes of the "pass" state's green (the viewer lightens state colours a little)
    lanes = _region(img, cells["states"]).astype(int)
    green = (lanes[..., 1] > lanes[..., 0] + 50) & (lanes[..., 1] > lanes[..., 2] + 50)
    assert np.count_nonzero(green) > 500
    # text log and legend: lines of text
    assert _ink(_region(img, cells["log"])) > 500, "text log empty"
    assert _ink(_region(img, cells["legend"])) > 500, "legend empty"
