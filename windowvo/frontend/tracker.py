"""Feature trackers with persistent track ids: pyramidal KLT (default) and ORB matching.

Both keep about ``max_features`` live tracks spread over a grid, give every track a
persistent id, and keep each live track's full pixel history. Where new corners go first when
the budget is short is ``frontend.detection_order`` (``grid_select``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..config import DetectionOrder, FrontendConfig
from ..runtime.stage_timer import Laps, Stage


@dataclass
class TrackSet:
    """Live tracks after a frame: ids, distorted pixel positions, and ages in frames."""

    ids: np.ndarray  # (N,) int64
    pixels: np.ndarray  # (N, 2) float32
    ages: np.ndarray  # (N,) int32
    n_detected: int = 0


class _History:
    """Pixel history of the live tracks, stored per frame as arrays (cheap to append).

    Frames older than the birth of the oldest live track are dropped, so every live track's
    full history is kept and memory stays bounded by the longest-lived track.
    """

    def __init__(self) -> None:
        self.frames: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, ids, pixels)

    def add(self, frame: int, ids: np.ndarray, pts: np.ndarray, ages: np.ndarray) -> None:
        self.frames.append((frame, ids.copy(), pts.copy()))
        oldest_birth = frame - int(ages.max()) if len(ages) else frame
        drop = 0
        while drop < len(self.frames) - 1 and self.frames[drop][0] < oldest_birth:
            drop += 1
        if drop:
            del self.frames[:drop]

    def get(self, track_id: int, last: int | None = None) -> list[tuple[int, float, float]]:
        out = []
        for frame, ids, pts in reversed(self.frames):
            hit = np.nonzero(ids == track_id)[0]
            if hit.size == 0:
                break
            out.append((frame, float(pts[hit[0], 0]), float(pts[hit[0], 1])))
            if last is not None and len(out) >= last:
                break
        return out[::-1]


def grid_cells(pixels: np.ndarray, shape: tuple[int, int], cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid cell (row, column) of each pixel (N,2) in an image of ``shape`` (h, w) cut into rows x cols."""
    h, w = shape
    pixels = np.asarray(pixels).reshape(-1, 2)
    cx = np.clip((pixels[:, 0] * cols / w).astype(int), 0, cols - 1)
    cy = np.clip((pixels[:, 1] * rows / h).astype(int), 0, rows - 1)
    return cy, cx


def cell_counts(pixels: np.ndarray, shape: tuple[int, int], cols: int, rows: int) -> np.ndarray:
    """Number of pixels in each grid cell, (rows, cols)."""
    counts = np.zeros((rows, cols), np.int32)
    if len(pixels):
        np.add.at(counts, grid_cells(pixels, shape, cols, rows), 1)
    return counts


def spread_order(candidates: np.ndarray, shape: tuple[int, int], cols: int, rows: int) -> np.ndarray:
    """Permutation of ``candidates`` (best first within each cell) into rounds of one per cell, bottom
    rows first within a round: a short budget then reaches every cell, the floor's rows first."""
    cy, cx = grid_cells(candidates, shape, cols, rows)
    cell = cy * cols + cx
    by_cell = np.argsort(cell, kind="stable")
    sorted_cells = cell[by_cell]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.empty(len(cell), np.int64)
    rank[by_cell] = np.arange(len(cell)) - first
    return np.lexsort((-cy, rank))


def grid_select(
    candidates: np.ndarray,
    existing: np.ndarray,
    shape: tuple[int, int],
    cols: int,
    rows: int,
    budget: int,
    per_cell: int,
    order: DetectionOrder = DetectionOrder.ROWS,
) -> np.ndarray:
    """Pick candidates into under-filled grid cells; returns their indices.

    Candidates come best first within each cell and cell by cell, top row first. ``rows`` takes them
    in that order, so a budget smaller than the cells' room fills the upper cells first (on KITTI 5 of
    200 fresh corners landed 4 deg or more below the horizon); ``spread`` takes one per cell per round
    (``spread_order``). ``auto`` is resolved before a tracker is built (``resolve_detection_order``)."""
    if len(candidates) == 0 or budget <= 0:
        return np.zeros(0, np.int64)
    perm = spread_order(candidates, shape, cols, rows) if order is DetectionOrder.SPREAD else None
    ordered = candidates if perm is None else candidates[perm]
    counts = cell_counts(existing, shape, cols, rows)
    ccy, ccx = grid_cells(ordered, shape, cols, rows)
    chosen = []
    for k in range(len(ordered)):
        if counts[ccy[k], ccx[k]] < per_cell:
            counts[ccy[k], ccx[k]] += 1
            chosen.append(k)
            if len(chosen) >= budget:
                break
    sel = np.asarray(chosen, np.int64)
    return sel if perm is None else perm[sel]


def resolve_detection_order(order: DetectionOrder, floor_only_scale: bool) -> DetectionOrder:
    """``auto``: spread when the floor is the run's only scale source (no wheel odometry, ground cue on):
    its landmarks then carry the scale, and a top-first detection leaves the floor's rows almost empty
    on a road; rows otherwise (measured on KITTI with wheels: the spread put the scale on grass and
    kerbs a few centimetres above the road, 06 with +2% wheels 0.31 -> 0.72 m)."""
    if order is not DetectionOrder.AUTO:
        return order
    return DetectionOrder.SPREAD if floor_only_scale else DetectionOrder.ROWS


class _TrackStore:
    """Live tracks (ids, pixels, ages) and their pixel history, shared by both trackers."""

    def __init__(self, cfg: FrontendConfig):
        self.cfg = cfg
        self.ids = np.zeros(0, np.int64)
        self.pts = np.zeros((0, 2), np.float32)
        self.ages = np.zeros(0, np.int32)
        self.next_id = 0
        self.frame = -1
        self._hist = _History()

    def history(self, track_id: int, last: int | None = None) -> list[tuple[int, float, float]]:
        """Pixel positions (frame, u, v) of a live track, oldest first (the last ``last`` only)."""
        return self._hist.get(int(track_id), last)

    def _keep(self, keep: np.ndarray) -> None:
        self.ids, self.pts, self.ages = self.ids[keep], self.pts[keep], self.ages[keep]

    def drop(self, ids: np.ndarray) -> None:
        """End the tracks ``ids`` (RANSAC outliers, rays outside the field of view)."""
        if len(ids):
            self._keep(~np.isin(self.ids, ids))


class KLTTracker(_TrackStore):
    """Shi-Tomasi corners on a grid, tracked with pyramidal Lucas-Kanade and a forward-backward check."""

    def __init__(self, cfg: FrontendConfig):
        super().__init__(cfg)
        self.prev_pyr: np.ndarray | None = None
        self.lk_win = (cfg.klt_window_px, cfg.klt_window_px)
        self.lk_crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)

    def track(self, image: np.ndarray, mask: np.ndarray | None = None) -> TrackSet:
        self.frame += 1
        lap = Laps()
        h, w = image.shape[:2]
        pyr = image  # the Python binding takes images, not prebuilt pyramids
        b = self.cfg.border_px
        if self.prev_pyr is not None and len(self.pts):
            p0 = self.pts.reshape(-1, 1, 2)
            lk = dict(winSize=self.lk_win, maxLevel=self.cfg.klt_levels, criteria=self.lk_crit)
            p1, st, err = cv2.calcOpticalFlowPyrLK(self.prev_pyr, pyr, p0, None, **lk)  # type: ignore[call-overload]
            p0b, stb, _ = cv2.calcOpticalFlowPyrLK(pyr, self.prev_pyr, p1, p0.copy(), **lk,  # type: ignore[call-overload]
                                                   flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
            p1 = p1.reshape(-1, 2)
            ok = (st.ravel() == 1) & (stb.ravel() == 1) & (fb < self.cfg.forward_backward_px)
            # KLT's residual (mean absolute grey difference of the patch): a patch that
            # deformed (strong perspective change, occlusion) tracks with a bias; end it.
            ok &= err.ravel() < self.cfg.klt_max_residual
            ok &= (p1[:, 0] >= b) & (p1[:, 1] >= b) & (p1[:, 0] < w - b) & (p1[:, 1] < h - b)
            if mask is not None and ok.any():
                xi = np.clip(p1[:, 0].astype(int), 0, w - 1)
                yi = np.clip(p1[:, 1].astype(int), 0, h - 1)
                ok &= mask[yi, xi] > 0
            self.ids, self.pts, self.ages = self.ids[ok], p1[ok].astype(np.float32), self.ages[ok] + 1
        self.prev_pyr = pyr
        lap(Stage.TRACKING)
        n_new = self._detect(image, mask)
        lap(Stage.DETECTION)
        self._hist.add(self.frame, self.ids, self.pts, self.ages)
        lap(Stage.TRACKING)
        return TrackSet(self.ids.copy(), self.pts.copy(), self.ages.copy(), n_new)

    def _grid_candidates(self, image: np.ndarray, m: np.ndarray, need: int) -> np.ndarray:
        """Shi-Tomasi corners, searched only in the grid cells that are short of tracks.

        Candidates come back sorted by corner quality within each cell; cost follows the
        area searched, so a frame that lost tracks only at one border stays cheap.
        """
        cfg = self.cfg
        h, w = image.shape[:2]
        cols, rows = cfg.grid_cols, cfg.grid_rows
        per_cell = int(np.ceil(cfg.max_features / (cols * rows)))
        counts = cell_counts(self.pts, (h, w), cols, rows)
        xs = np.linspace(0, w, cols + 1).astype(int)
        ys = np.linspace(0, h, rows + 1).astype(int)
        out = []
        for r in range(rows):
            for c in range(cols):
                want = per_cell - counts[r, c]
                if want <= 0:
                    continue
                roi_m = m[ys[r] : ys[r + 1], xs[c] : xs[c + 1]]
                if not roi_m.any():
                    continue
                found = cv2.goodFeaturesToTrack(image[ys[r] : ys[r + 1], xs[c] : xs[c + 1]], maxCorners=int(2 * want),
                                                qualityLevel=cfg.quality_level, minDistance=cfg.min_distance_px,
                                                mask=roi_m, blockSize=5)
                if found is not None:
                    out.append(found.reshape(-1, 2) + [xs[c], ys[r]])
        if not out:
            return np.zeros((0, 2), np.float32)
        return np.concatenate(out).astype(np.float32)

    def _detect(self, image: np.ndarray, mask: np.ndarray | None) -> int:
        cfg = self.cfg
        need = cfg.max_features - len(self.ids)
        if need < max(5, cfg.max_features // 10):
            return 0
        h, w = image.shape[:2]
        b = cfg.border_px
        m = np.zeros((h, w), np.uint8)
        m[b : h - b, b : w - b] = 255
        if mask is not None:
            m &= np.where(mask > 0, 255, 0).astype(np.uint8)
        r = round(cfg.min_distance_px)
        for x, y in self.pts.astype(int):
            cv2.circle(m, (int(x), int(y)), r, 0, -1)
        cand = self._grid_candidates(image, m, need)
        if len(cand) == 0:
            return 0
        cells = cfg.grid_cols * cfg.grid_rows
        per_cell = int(np.ceil(1.5 * cfg.max_features / cells))
        sel = grid_select(cand, self.pts, (h, w), cfg.grid_cols, cfg.grid_rows, need, per_cell,
                          cfg.detection_order)
        if sel.size == 0:
            return 0
        new_pts = cand[sel].astype(np.float32)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        new_pts = cv2.cornerSubPix(image, new_pts.reshape(-1, 1, 2), (3, 3), (-1, -1), crit).reshape(-1, 2)
        new_ids = np.arange(self.next_id, self.next_id + len(new_pts), dtype=np.int64)
        self.next_id += len(new_pts)
        self.ids = np.concatenate([self.ids, new_ids])
        self.pts = np.concatenate([self.pts, new_pts.astype(np.float32)])
        self.ages = np.concatenate([self.ages, np.zeros(len(new_pts), np.int32)])
        return len(new_pts)


class ORBTracker(_TrackStore):
    """The textbook alternative: ORB keypoints matched frame to frame (Hamming, ratio test)."""

    def __init__(self, cfg: FrontendConfig):
        super().__init__(cfg)
        self.orb = cv2.ORB.create(nfeatures=int(cfg.max_features * 2), fastThreshold=10)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.desc: np.ndarray | None = None

    def _keep(self, keep: np.ndarray) -> None:
        super()._keep(keep)
        if self.desc is not None:
            self.desc = self.desc[keep]

    def track(self, image: np.ndarray, mask: np.ndarray | None = None) -> TrackSet:
        self.frame += 1
        lap = Laps()
        h, w = image.shape[:2]
        kps, desc = self.orb.detectAndCompute(image, mask)
        lap(Stage.DETECTION)
        if desc is None or len(kps) == 0:
            self.ids, self.pts, self.ages, self.desc = self.ids[:0], self.pts[:0], self.ages[:0], None
            return TrackSet(self.ids.copy(), self.pts.copy(), self.ages.copy(), 0)
        pts = np.array([k.pt for k in kps], np.float32)
        resp = np.array([k.response for k in kps])
        order = np.argsort(-resp)
        pts, desc = pts[order], desc[order]
        new_ids = np.full(len(pts), -1, np.int64)
        new_ages = np.zeros(len(pts), np.int32)
        if self.desc is not None and len(self.desc) >= 2 and len(desc) >= 2:
            matches = self.matcher.knnMatch(desc, self.desc, k=2)
            used = set()
            for mlist in matches:
                if len(mlist) < 2:
                    continue
                m, n = mlist
                if (m.distance < 0.75 * n.distance and m.trainIdx not in used
                        and np.linalg.norm(pts[m.queryIdx] - self.pts[m.trainIdx]) < 0.25 * max(h, w)):
                    used.add(m.trainIdx)
                    new_ids[m.queryIdx] = self.ids[m.trainIdx]
                    new_ages[m.queryIdx] = self.ages[m.trainIdx] + 1
        matched = new_ids >= 0
        lap(Stage.TRACKING)
        budget = max(self.cfg.max_features - int(matched.sum()), 0)
        cells = self.cfg.grid_cols * self.cfg.grid_rows
        per_cell = int(np.ceil(1.5 * self.cfg.max_features / cells))
        free = np.nonzero(~matched)[0]
        sel = free[grid_select(pts[free], pts[matched], (h, w), self.cfg.grid_cols, self.cfg.grid_rows, budget, per_cell,
                               self.cfg.detection_order)]
        n_new = len(sel)
        new_ids[sel] = np.arange(self.next_id, self.next_id + n_new)
        self.next_id += n_new
        keep = new_ids >= 0
        self.ids, self.pts, self.ages, self.desc = new_ids[keep], pts[keep], new_ages[keep], desc[keep]
        self._hist.add(self.frame, self.ids, self.pts, self.ages)
        lap(Stage.DETECTION)  # choosing the new tracks
        return TrackSet(self.ids.copy(), self.pts.copy(), self.ages.copy(), n_new)
