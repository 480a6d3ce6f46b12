"""Feature trackers with persistent track ids: pyramidal KLT (default) and ORB matching.

Both keep about ``max_features`` live tracks spread over a grid, give every track a
persistent id, and keep each live track's full pixel history. Where new corners go first when
the budget is short is ``frontend.detection_order`` (``grid_select``).
"""

from __future__ import annotations

from collections.abc import Iterator
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
    if not len(pixels):
        return np.zeros((rows, cols), np.int32)
    cy, cx = grid_cells(pixels, shape, cols, rows)
    return np.bincount(cy * cols + cx, minlength=rows * cols).astype(np.int32).reshape(rows, cols)


def rank_within(groups: np.ndarray) -> np.ndarray:
    """Each element's rank (0, 1, ...) among the elements of its group, in their order: [3, 1, 3, 3] -> [0, 0, 1, 2]."""
    by_group = np.argsort(groups, kind="stable")
    sorted_groups = groups[by_group]
    first = np.searchsorted(sorted_groups, sorted_groups, side="left")
    rank = np.empty(len(groups), np.int64)
    rank[by_group] = np.arange(len(groups)) - first
    return rank


def spread_order(candidates: np.ndarray, shape: tuple[int, int], cols: int, rows: int) -> np.ndarray:
    """Permutation of ``candidates`` (best first within each cell) into rounds of one per cell, bottom
    rows first within a round: a short budget then reaches every cell, the floor's rows first."""
    cy, cx = grid_cells(candidates, shape, cols, rows)
    return np.lexsort((-cy, rank_within(cy * cols + cx)))


class GridFill:
    """Candidates taken in the order given into grid cells holding fewer than ``per_cell`` points (the
    ``existing`` ones and those taken), until ``budget`` are taken; fed in batches (``take``), the same
    choice as one pass over their concatenation, so a caller can stop detecting once the budget is full."""

    def __init__(self, existing: np.ndarray, shape: tuple[int, int], cols: int, rows: int, budget: int,
                 per_cell: int):
        self.shape, self.cols, self.rows = shape, cols, rows
        self.counts = cell_counts(existing, shape, cols, rows).reshape(-1)
        self.room = max(budget, 0)
        self.per_cell = per_cell

    @property
    def full(self) -> bool:
        return self.room <= 0

    def take(self, candidates: np.ndarray) -> np.ndarray:
        """Indices of the candidates taken, in their order. In a cell, the first ones while it has room."""
        if self.full or len(candidates) == 0:
            return np.zeros(0, np.int64)
        cy, cx = grid_cells(candidates, self.shape, self.cols, self.rows)
        cell = cy * self.cols + cx
        fits = rank_within(cell) < self.per_cell - self.counts[cell]
        sel = np.nonzero(fits)[0][: self.room]
        self.counts += np.bincount(cell[sel], minlength=self.counts.size).astype(np.int32)
        self.room -= len(sel)
        return sel.astype(np.int64)


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
    sel = GridFill(existing, shape, cols, rows, budget, per_cell).take(ordered)
    return sel if perm is None else perm[sel]


def resolve_detection_order(order: DetectionOrder, floor_only_scale: bool) -> DetectionOrder:
    """``auto``: spread when the floor is the run's only scale source (no wheel odometry, ground cue on):
    its landmarks then carry the scale, and a top-first detection leaves the floor's rows almost empty
    on a road; rows otherwise (measured on KITTI with wheels: the spread put the scale on grass and
    kerbs a few centimetres above the road, 06 with +2% wheels 0.31 -> 0.72 m). With wheels the front end turns rows to
    spread later if the base rocks on its suspension (``frontend/rocking.py``)."""
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
    """Shi-Tomasi corners on a grid, tracked with pyramidal Lucas-Kanade and a forward-backward check; with
    ``frontend.klt_highpass_px`` each match is placed again on the images less their local means (``_refine``)."""

    def __init__(self, cfg: FrontendConfig):
        super().__init__(cfg)
        self.prev_pyr: np.ndarray | None = None
        self.prev_hp: np.ndarray | None = None  # the previous frame less its local mean (klt_highpass_px)
        self.lk_win = (cfg.klt_window_px, cfg.klt_window_px)
        self.lk_crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        self._base_mask: tuple[tuple[int, int], np.ndarray | None, np.ndarray] | None = None

    def track(self, image: np.ndarray, mask: np.ndarray | None = None) -> TrackSet:
        self.frame += 1
        lap = Laps()
        pyr = image  # images: the Python binding takes no prebuilt pyramid
        hp = self._tracking_image(image) if self.cfg.klt_highpass_px > 0 else None
        if self.prev_pyr is not None and len(self.pts):
            ok, p1 = self._flow(self.prev_pyr, pyr, mask, self.prev_hp, hp)
            self.ids, self.pts, self.ages = self.ids[ok], p1[ok].astype(np.float32), self.ages[ok] + 1
        self.prev_pyr, self.prev_hp = pyr, hp
        lap(Stage.TRACKING)
        n_new = self._detect(image, mask)
        lap(Stage.DETECTION)
        self._hist.add(self.frame, self.ids, self.pts, self.ages)
        lap(Stage.TRACKING)
        return TrackSet(self.ids.copy(), self.pts.copy(), self.ages.copy(), n_new)

    def _tracking_image(self, image: np.ndarray) -> np.ndarray:
        """The image less its local mean (``klt_highpass_px`` box), offset to mid-grey, where KLT's matches are
        placed: a brightness change that is locally linear (a sheen that moves with the view, shading) cancels
        in it, so the patches' match is not pulled along its gradient."""
        b = self.cfg.klt_highpass_px
        mean: np.ndarray = cv2.boxFilter(image, cv2.CV_32F, (b, b), borderType=cv2.BORDER_REFLECT)  # float: no steps
        np.subtract(mean, np.float32(128.0), out=mean)
        return cv2.subtract(image, mean, dtype=cv2.CV_8U)  # image - mean + 128, rounded and saturated

    def _refine(self, a_hp: np.ndarray, b_hp: np.ndarray, pa: np.ndarray, pb: np.ndarray, st: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pyramid's matches ``pb`` (of ``pa``) placed again on the finest level of the images less their
        local means: the coarse levels of a high-passed image keep too little to search with, so the search
        stays on the images and only the final placement assumes brightness constancy up to a local linear
        change. Status: both passes'; residual: the refinement's."""
        pb, st2, err = cv2.calcOpticalFlowPyrLK(a_hp, b_hp, pa, pb.copy(), winSize=self.lk_win, maxLevel=0,
                                                criteria=self.lk_crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        return pb, st & st2, err

    def _flow(self, prev: np.ndarray, image: np.ndarray, mask: np.ndarray | None, prev_hp: np.ndarray | None = None,
              image_hp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The live tracks' new pixels (N, 2) and which of them survive the checks (N,) bool.

        The backward flow runs only for the tracks the forward flow's own checks (status, residual, border,
        mask) keep: Lucas-Kanade tracks every point on its own, so the others' results are the same."""
        h, w = image.shape[:2]
        b = self.cfg.border_px
        p0 = self.pts.reshape(-1, 1, 2)
        lk = dict(winSize=self.lk_win, maxLevel=self.cfg.klt_levels, criteria=self.lk_crit)
        p1, st, err = cv2.calcOpticalFlowPyrLK(prev, image, p0, None, **lk)  # type: ignore[call-overload]
        if prev_hp is not None and image_hp is not None:  # klt_highpass_px
            p1, st, err = self._refine(prev_hp, image_hp, p0, p1, st)
        p1 = p1.reshape(-1, 2)
        # KLT's residual (mean absolute grey difference of the patch): a patch that
        # deformed (strong perspective change, occlusion) tracks with a bias; end it.
        ok = (st.ravel() == 1) & (err.ravel() < self.cfg.klt_max_residual)
        ok &= (p1[:, 0] >= b) & (p1[:, 1] >= b) & (p1[:, 0] < w - b) & (p1[:, 1] < h - b)
        if mask is not None and ok.any():
            xi = np.clip(p1[:, 0].astype(int), 0, w - 1)
            yi = np.clip(p1[:, 1].astype(int), 0, h - 1)
            ok &= mask[yi, xi] > 0
        fwd = np.nonzero(ok)[0]
        if fwd.size:
            p0f = p0[fwd]
            p1f = p1[fwd].reshape(-1, 1, 2)
            p0b, stb, _ = cv2.calcOpticalFlowPyrLK(image, prev, p1f, p0f.copy(), **lk,  # type: ignore[call-overload]
                                                   flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            if prev_hp is not None and image_hp is not None:
                p0b, stb, _ = self._refine(image_hp, prev_hp, p1f, p0b, stb)
            fb = np.linalg.norm((p0b - p0f).reshape(-1, 2), axis=1)
            ok[fwd] = (stb.ravel() == 1) & (fb < self.cfg.forward_backward_px)
        return ok, p1

    def _cell_candidates(self, image: np.ndarray, m: np.ndarray) -> Iterator[np.ndarray]:
        """Shi-Tomasi corners (K, 2) float32 of each grid cell short of tracks, cell by cell, top row first.

        Searched only in those cells (cost follows the area searched), each sorted by corner quality
        relative to the best corner of its cell; lazily, so a caller whose budget is full stops early.
        """
        cfg = self.cfg
        h, w = image.shape[:2]
        cols, rows = cfg.grid_cols, cfg.grid_rows
        per_cell = int(np.ceil(cfg.max_features / (cols * rows)))
        counts = cell_counts(self.pts, (h, w), cols, rows)
        xs = np.linspace(0, w, cols + 1).astype(int)
        ys = np.linspace(0, h, rows + 1).astype(int)
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
                    yield (found.reshape(-1, 2) + [xs[c], ys[r]]).astype(np.float32)

    def _detection_mask(self, shape: tuple[int, int], mask: np.ndarray | None) -> np.ndarray:
        """255 where a new corner may go: inside the border, the mask and away from the live tracks. The part
        without the tracks is kept while the same mask object (or none) comes with frames of one size."""
        base = self._base_mask
        if base is None or base[0] != shape or base[1] is not mask:
            h, w = shape
            b = self.cfg.border_px
            m = np.zeros((h, w), np.uint8)
            m[b : h - b, b : w - b] = 255
            if mask is not None:
                m &= np.where(mask > 0, 255, 0).astype(np.uint8)
            base = self._base_mask = (shape, mask, m)
        m = base[2].copy()
        r = round(self.cfg.min_distance_px)
        for x, y in self.pts.astype(int):
            cv2.circle(m, (int(x), int(y)), r, 0, -1)
        return m

    def _new_corners(self, image: np.ndarray, mask: np.ndarray | None, need: int) -> np.ndarray:
        """The new corners (K, 2) float32 in the order ``grid_select`` would take them from every short cell's.

        In the ``rows`` order each cell's corners are taken before the next cell's are needed, so detection
        stops at the cell that fills the budget (on KITTI after 24 of 41 short cells); ``spread`` needs all.
        The cells' corners are taken in batches, once they could fill the budget (the same choice, ``GridFill``)."""
        cfg = self.cfg
        h, w = image.shape[:2]
        cells = self._cell_candidates(image, self._detection_mask((h, w), mask))
        per_cell = int(np.ceil(1.5 * cfg.max_features / (cfg.grid_cols * cfg.grid_rows)))
        if cfg.detection_order is DetectionOrder.SPREAD:
            found = list(cells)
            if not found:
                return np.zeros((0, 2), np.float32)
            cand = np.concatenate(found)
            sel = grid_select(cand, self.pts, (h, w), cfg.grid_cols, cfg.grid_rows, need, per_cell,
                              cfg.detection_order)
            return cand[sel]
        fill = GridFill(self.pts, (h, w), cfg.grid_cols, cfg.grid_rows, need, per_cell)
        taken: list[np.ndarray] = []
        pending: list[np.ndarray] = []
        n_pending = 0
        for cand in cells:
            pending.append(cand)
            n_pending += len(cand)
            if n_pending >= fill.room:  # the budget may be full now: take (a batch costs the same as one cell)
                batch = np.concatenate(pending)
                taken.append(batch[fill.take(batch)])
                pending, n_pending = [], 0
                if fill.full:
                    break
        if pending:
            batch = np.concatenate(pending)
            taken.append(batch[fill.take(batch)])
        return np.concatenate(taken) if taken else np.zeros((0, 2), np.float32)

    def _detect(self, image: np.ndarray, mask: np.ndarray | None) -> int:
        cfg = self.cfg
        need = cfg.max_features - len(self.ids)
        if need < max(5, cfg.max_features // 10):
            return 0
        new_pts = self._new_corners(image, mask, need)
        if len(new_pts) == 0:
            return 0
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
