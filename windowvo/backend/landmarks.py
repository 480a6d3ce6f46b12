"""Landmark manager of the back end: observations, triangulation, lifecycle and outliers.

A track's observations are collected per keyframe until enough keyframes have seen it; then it
is triangulated (midpoint over the window, with angle, depth and reprojection checks) and becomes
a landmark ``L(id)`` in the smoother. A landmark lives while keyframes in the window see it,
is dropped as an outlier when its reprojection error stays large, and is forgotten once the
smoother marginalises the last keyframe that saw it. This module never calls the smoother: it
decides which landmarks and factors to add or remove, and the window (``smoother.py``) submits them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import gtsam
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig
from ..geometry import inv_T
from .factors import G, L, X

# Minimum correspondences for PnP on the window's landmarks, and inliers to accept its pose.
PNP_MIN_POINTS = 12
PNP_MIN_INLIERS = 10
# Points closer than this to a camera (m) count as behind it.
MIN_DEPTH_M = 0.05
# Reprojection errors above this are clamped in the RMS diagnostic (one gross outlier must not hide the rest).
RMS_CLAMP_PX = 50.0
# Dead track ids are only remembered while the front end may still report them.
MAX_DEAD_IDS, KEEP_DEAD_IDS = 50_000, 20_000


@dataclass
class SmartTrack:
    """A landmark kept as a smart projection factor (``backend.landmark_model: smart``): no point state; its
    observations in the window and the factor over them now in the smoother. A new observation replaces the
    factor (a fresh one over all the observations; the old one's slot is removed in the same update)."""

    observations: list[tuple[int, np.ndarray, float]]  # (keyframe, undistorted px, noise stretch), keyframe order
    factor: gtsam.SmartProjectionPoseFactorCal3_S2 | None = None  # the one in the smoother

    @property
    def first_kf(self) -> int:
        """The oldest keyframe it observes: its factor is marginalised (gone from the smoother) when that leaves."""
        return self.observations[0][0]

    def point(self, estimate: gtsam.Values) -> np.ndarray | None:
        """p_world_landmark triangulated by its factor from the poses of ``estimate`` (None: degenerate, behind a
        camera, too far, an outlier, or its factor no longer in the window)."""
        if self.factor is None or not estimate.exists(X(self.first_kf)):
            return None
        result = self.factor.point(estimate)
        return np.asarray(result.get(), float) if result.valid() else None


@dataclass
class LandmarkState:
    key: int
    last_kf: int
    # (keyframe, smoother factor index); of a smart landmark, the one of its factor with its oldest keyframe.
    factor_indices: list[tuple[int, int]] = field(default_factory=list)
    strikes: int = 0
    on_ground: bool = False
    ground_factor: tuple[int, int] | None = None  # (keyframe, smoother factor index) of its native ground factor
    smart: SmartTrack | None = None  # a smart landmark (no point state L(id) in the smoother)


def reprojection_errors(camera: CameraModel, T_world_base: np.ndarray, T_base_cam: np.ndarray,
                        p_world: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel errors of world points (N,3) against undistorted pixels (N,2); inf behind the camera."""
    if len(p_world) == 0:
        return np.zeros(0)
    T_cw = inv_T(T_world_base @ T_base_cam)
    pc = np.asarray(p_world) @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = pc[:, 2]
    safe = np.where(z > MIN_DEPTH_M, z, 1.0)
    proj = np.stack([camera.fx * pc[:, 0] / safe + camera.cx, camera.fy * pc[:, 1] / safe + camera.cy], axis=1)
    err = np.linalg.norm(proj - np.asarray(uv), axis=1)
    return np.where(z > MIN_DEPTH_M, err, np.inf)


def reprojection_rms(errors: np.ndarray) -> float:
    if len(errors) == 0:
        return float("nan")
    return float(np.sqrt(np.mean(np.square(np.minimum(errors, RMS_CLAMP_PX)))))


class LandmarkManager:
    """Observations of tracks and the lifecycle of the landmarks made from them."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig):
        self.camera = camera
        self.cfg = cfg
        self.T_base_cam = camera.T_base_cam
        self._cos_min_angle = float(np.cos(np.radians(cfg.min_triangulation_angle_deg)))
        # track id -> [(k, undistorted px, pixel-noise stretch of the lens at that observation)]
        self.obs: dict[int, list[tuple[int, np.ndarray, float]]] = {}
        self.landmarks: dict[int, LandmarkState] = {}
        self.dead: set[int] = set()
        self.pending_removal: list[int] = []  # smoother factor indices to remove at the next update
        self._where: dict[int, np.ndarray] = {}  # track id -> p_world_landmark in the last estimate

    # ------------------------------------------------------------------ queries
    def read_estimate(self, estimate: gtsam.Values | None) -> None:
        """Read every landmark's position from a new estimate, once: the queries below use these until
        the next estimate (each read from GTSAM costs about a microsecond per landmark, and several
        queries per keyframe would repeat it)."""
        self._where = {}
        if estimate is None:
            return
        for tid, lm in self.landmarks.items():
            if lm.smart is not None:
                p = lm.smart.point(estimate)
                if p is not None:
                    self._where[tid] = p
            elif estimate.exists(lm.key):
                self._where[tid] = estimate.atPoint3(lm.key)

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Track ids and world positions of the landmarks in the last estimate (still alive)."""
        ids = [tid for tid in self.landmarks if tid in self._where]
        pts = [self._where[tid] for tid in ids]
        return np.asarray(ids, np.int64), np.asarray(pts, float).reshape(-1, 3)

    def seen_now(self, fo_ids: np.ndarray, uv: np.ndarray, k: int) -> tuple[list[int], np.ndarray, np.ndarray]:
        """Landmarks observed at keyframe k: ids, world positions (last estimate), undistorted pixels."""
        ids, pts, pix = [], [], []
        for tid, p in zip(fo_ids.tolist(), uv):
            lm = self.landmarks.get(tid)
            if lm is None or lm.last_kf != k or tid not in self._where:
                continue
            ids.append(tid)
            pts.append(self._where[tid])
            pix.append(p)
        return ids, np.asarray(pts, float).reshape(-1, 3), np.asarray(pix, float).reshape(-1, 2)

    def pnp_pose(self, fo_ids: np.ndarray, uv: np.ndarray, pixel_sigma: float) -> np.ndarray | None:
        """T_world_base from the window's landmarks seen in this frame (EPnP in RANSAC), or None."""
        pts3, pts2 = [], []
        for tid, p in zip(fo_ids.tolist(), uv):
            if tid in self.landmarks and tid in self._where:
                pts3.append(self._where[tid])
                pts2.append(p)
        if len(pts3) < PNP_MIN_POINTS:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            np.asarray(pts3, np.float64), np.asarray(pts2, np.float64), self.camera.K, None,
            reprojectionError=2.0 * pixel_sigma + 1.0, iterationsCount=100, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < PNP_MIN_INLIERS:
            return None
        R, _ = cv2.Rodrigues(rvec)
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = R
        T_cam_world[:3, 3] = tvec.ravel()
        return inv_T(T_cam_world) @ inv_T(self.T_base_cam)

    # ------------------------------------------------------------------ observations
    def observe(self, fo_ids: np.ndarray, uv: np.ndarray, k: int, allow_new: bool, stretch: np.ndarray | None = None,
                window_start: int = 0) -> tuple[list[tuple[int, np.ndarray, float]], list[int]]:
        """Sort this keyframe's tracks: observations of existing landmarks, and tracks ready to triangulate.

        Returns ``(seen, candidates)``: (track id, pixel, noise stretch) of live landmarks (their timestamps
        must be refreshed), and ids of tracks seen by enough keyframes, longest first. ``stretch`` is the
        lens's pixel-noise stretch per track (1 for a pinhole; ``FrontendOutput.pixel_sigma_scale``).
        A smart landmark takes the observation into its track; one whose factor this update marginalises
        (its oldest keyframe before ``window_start``) ends there, and its track starts afresh from this
        observation (as Kimera-VIO's: what the old factor knew stays in the marginal).
        """
        seen: list[tuple[int, np.ndarray, float]] = []
        candidates: list[int] = []
        st = np.ones(len(fo_ids)) if stretch is None else np.asarray(stretch, float)
        for tid, p, sc in zip(fo_ids.tolist(), uv, st.tolist()):
            if tid in self.dead:
                continue
            lm = self.landmarks.get(tid)
            if lm is not None and lm.smart is not None and lm.smart.first_kf < window_start:
                del self.landmarks[tid]
                lm = None
            if lm is not None:
                lm.last_kf = k
                if lm.smart is not None:
                    lm.smart.observations.append((k, np.asarray(p, float), sc))
                seen.append((tid, p, sc))
                continue
            lst = self.obs.setdefault(tid, [])
            lst.append((k, np.asarray(p, float), sc))
            if allow_new and len(lst) >= self.cfg.min_landmark_observations:
                candidates.append(tid)
        candidates.sort(key=lambda t: -len(self.obs[t]))
        return seen, candidates

    def budgets(self, max_floor: int, seen_since: int = 0, in_view_since: int | None = None) -> tuple[int, int]:
        """Room left for new landmarks: (others, floor landmarks). Only landmarks seen by keyframe
        ``seen_since`` or later count (those waiting for their block's marginalisation do not). With
        ``in_view_since`` and ``min_landmarks_in_view``: the others' room is at least what brings the landmarks
        seen by keyframe ``in_view_since`` or later (those still in view) up to that minimum (at most ``max_landmarks``)."""
        live = [lm for lm in self.landmarks.values() if lm.last_kf >= seen_since]
        n_floor = sum(1 for lm in live if lm.on_ground)
        room = self.cfg.max_landmarks - (len(live) - n_floor)
        if in_view_since is not None and self.cfg.min_landmarks_in_view > 0:
            in_view = sum(1 for lm in self.landmarks.values() if lm.last_kf >= in_view_since and not lm.on_ground)
            room = max(room, min(self.cfg.min_landmarks_in_view, self.cfg.max_landmarks) - in_view)
        return room, max_floor - n_floor

    # ------------------------------------------------------------------ triangulation
    @staticmethod
    def camera_poses(T_world_base: dict[int, np.ndarray], T_base_cam: np.ndarray
                     ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """T_world_cam rotation and centre per keyframe, computed once per update."""
        out = {}
        for kk, T in T_world_base.items():
            T_wc = T @ T_base_cam
            out[kk] = (T_wc[:3, :3], T_wc[:3, 3])
        return out

    def triangulate(self, tids: list[int], cams: dict[int, tuple[np.ndarray, np.ndarray]]
                    ) -> list[np.ndarray | None]:
        """Midpoint triangulation of tracks over the window, with angle, depth and reprojection checks."""
        tracks = [[(kk, p) for kk, p, _ in self.obs.get(tid, []) if kk in cams] for tid in tids]
        return triangulate_many(self.camera, self.cfg, tracks, cams, self._cos_min_angle)

    def promote(self, tid: int, k: int, on_ground: bool) -> list[tuple[int, np.ndarray, float]]:
        """Turn a triangulated track into a landmark; returns its stored observations."""
        self.landmarks[tid] = LandmarkState(G(tid) if on_ground else L(tid), k, on_ground=on_ground)
        return self.obs.pop(tid)

    def promote_smart(self, tid: int, k: int, window_start: int) -> SmartTrack:
        """Turn a triangulated track into a smart landmark over its observations in the window."""
        track = SmartTrack([o for o in self.obs.pop(tid) if o[0] >= window_start])
        self.landmarks[tid] = LandmarkState(L(tid), k, smart=track)
        return track

    def replace_smart(self, tid: int) -> None:
        """A smart landmark's factor is replaced in this update: its old slot is removed in it."""
        lm = self.landmarks[tid]
        self.pending_removal.extend(fi for _, fi in lm.factor_indices)
        lm.factor_indices.clear()

    def record_factors(self, owners: list[tuple[int, int, bool] | None], indices: list[int]) -> None:
        """Remember the smoother's index of each factor a landmark owns, per (track id, keyframe, is its
        native ground factor)."""
        for fi, owner in zip(indices, owners):
            if owner is not None and owner[0] in self.landmarks:
                lm = self.landmarks[owner[0]]
                lm.factor_indices.append((owner[1], int(fi)))
                if owner[2]:
                    lm.ground_factor = (owner[1], int(fi))

    def drop_factor(self, tid: int, k: int, index: int) -> None:
        """Forget a factor of a landmark that the caller removes from the smoother (its slot may be reused)."""
        lm = self.landmarks[tid]
        lm.factor_indices.remove((k, index))
        if lm.ground_factor == (k, index):
            lm.ground_factor = None

    def tied_to_floor(self, window_start: int) -> list[tuple[int, int, int, np.ndarray]]:
        """Landmarks whose native ground factor ties them to a keyframe still in the window, with a position in
        the last estimate: (track id, that keyframe, the factor's smoother index, p_world_landmark)."""
        out = []
        for tid, lm in self.landmarks.items():
            if lm.ground_factor is None or lm.ground_factor[0] < window_start:
                continue
            p_world = self._where.get(tid)
            if p_world is not None:
                out.append((tid, *lm.ground_factor, p_world))
        return out

    def n_tied_to_floor(self, window_start: int) -> int:
        """How many landmarks a native ground factor ties to a keyframe still in the window."""
        return sum(lm.ground_factor is not None and lm.ground_factor[0] >= window_start
                   for lm in self.landmarks.values())

    def position(self, tid: int) -> np.ndarray | None:
        """A landmark's world position in the last estimate (None if it has none)."""
        return self._where.get(tid)

    def forget(self, tids: list[int]) -> None:
        for tid in tids:
            self.landmarks.pop(tid, None)
            self.dead.add(tid)

    # ------------------------------------------------------------------ lifecycle
    def prune(self, window_start: int) -> None:
        """Forget the bookkeeping of landmarks and observations the smoother has marginalised. A smart landmark
        whose factor was marginalised ends (its track may start afresh, see ``observe``)."""
        self.forget([t for t, lm in self.landmarks.items() if lm.last_kf < window_start])
        for tid in [t for t, lm in self.landmarks.items() if lm.smart is not None and lm.smart.first_kf < window_start]:
            del self.landmarks[tid]
        for tid, track in list(self.obs.items()):
            if track[0][0] >= window_start:  # observations are in keyframe order: nothing to drop
                continue
            kept = [o for o in track if o[0] >= window_start]
            if kept:
                self.obs[tid] = kept
            else:
                del self.obs[tid]
        if len(self.dead) > MAX_DEAD_IDS:
            self.dead = set(sorted(self.dead)[-KEEP_DEAD_IDS:])

    def check_outliers(self, ids: list[int], errors: np.ndarray, next_window_start: int) -> None:
        """Landmarks whose reprojection error stays large on two keyframes are dropped; their factors
        on poses still in the window are removed at the next update."""
        for tid, err in zip(ids, errors):
            lm = self.landmarks.get(tid)
            if lm is None:
                continue
            if err > self.cfg.outlier_residual_px:
                lm.strikes += 1
                if lm.strikes >= 2:
                    self.pending_removal.extend(fi for kk, fi in lm.factor_indices if kk >= next_window_start)
                    self.forget([tid])
            else:
                lm.strikes = 0

    def take_removals(self) -> list[int]:
        out, self.pending_removal = self.pending_removal, []
        return out

    def restart(self, k: int, fo_ids: np.ndarray, uv: np.ndarray, stretch: np.ndarray | None = None) -> None:
        """After a reset: every landmark is gone; this keyframe's observations seed new ones."""
        self.dead.update(self.landmarks)
        self.landmarks.clear()
        self.obs.clear()
        self._where = {}
        self.pending_removal = []
        st = np.ones(len(fo_ids)) if stretch is None else np.asarray(stretch, float)
        for tid, p, sc in zip(fo_ids.tolist(), uv, st.tolist()):
            self.obs[tid] = [(k, np.asarray(p, float), sc)]
        self.dead.difference_update(fo_ids.tolist())


def triangulate_midpoint(camera: CameraModel, cfg: BackendConfig, obs: list[tuple[int, np.ndarray]],
                         cams: dict[int, tuple[np.ndarray, np.ndarray]], cos_min_angle: float) -> np.ndarray | None:
    """Point closest to the rays of the observations (undistorted pixels), or None if it fails a check:
    rays too parallel, behind or too far from a camera, or reprojecting badly."""
    return triangulate_many(camera, cfg, [obs], cams, cos_min_angle)[0]


def triangulate_many(camera: CameraModel, cfg: BackendConfig, tracks: list[list[tuple[int, np.ndarray]]],
                     cams: dict[int, tuple[np.ndarray, np.ndarray]], cos_min_angle: float
                     ) -> list[np.ndarray | None]:
    """``triangulate_midpoint`` of many tracks at once (their observations padded to one length)."""
    out: list[np.ndarray | None] = [None] * len(tracks)
    idx = [i for i, obs in enumerate(tracks) if len(obs) >= 2]
    if not idx:
        return out
    K = camera
    m = max(len(tracks[i]) for i in idx)
    n = len(idx)
    # Every observation's (row, column, keyframe, pixel), then placed into the padded arrays at once.
    lengths = np.asarray([len(tracks[i]) for i in idx])
    rows_flat = np.repeat(np.arange(n), lengths)
    cols_flat = np.arange(len(rows_flat)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    kf_flat = [kk for i in idx for kk, _ in tracks[i]]
    kf_order = sorted(set(kf_flat))
    slot = {kk: j for j, kk in enumerate(kf_order)}
    kf_R = np.stack([cams[kk][0] for kk in kf_order])
    kf_c = np.stack([cams[kk][1] for kk in kf_order])
    which = np.asarray([slot[kk] for kk in kf_flat])
    valid = np.zeros((n, m), bool)
    valid[rows_flat, cols_flat] = True
    uv = np.zeros((n, m, 2))
    uv[rows_flat, cols_flat] = np.asarray([p for i in idx for _, p in tracks[i]], float).reshape(-1, 2)
    R = np.tile(np.eye(3), (n, m, 1, 1))  # R_world_cam per observation
    R[rows_flat, cols_flat] = kf_R[which]
    c = np.zeros((n, m, 3))  # camera centres
    c[rows_flat, cols_flat] = kf_c[which]
    last = lengths - 1
    rays_c = np.stack([(uv[..., 0] - K.cx) / K.fx, (uv[..., 1] - K.cy) / K.fy, np.ones((n, m))], axis=-1)
    d = np.einsum("nmij,nmj->nmi", R, rays_c)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    # The rays of the first and the last observation must diverge (then the widest pair does too).
    rows = np.arange(n)
    ok = np.einsum("ni,ni->n", d[:, 0], d[rows, last]) <= cos_min_angle
    P = np.eye(3) - d[..., :, None] * d[..., None, :]
    P *= valid[..., None, None]
    A = P.sum(axis=1)
    b = np.einsum("nmij,nmj->ni", P, c)
    ok &= np.linalg.det(A) >= 1e-9
    A[~ok] = np.eye(3)
    p = np.linalg.solve(A, b[..., None])[..., 0]
    pc = np.einsum("nmji,nmj->nmi", R, p[:, None, :] - c)  # R^T (p - c)
    z = np.where(valid, pc[..., 2], 1.0)
    ok &= np.all((z > 0.1) & (z <= cfg.max_landmark_depth_m), axis=1)
    zs = np.where(z > 1e-9, z, 1.0)
    proj = np.stack([K.fx * pc[..., 0] / zs + K.cx, K.fy * pc[..., 1] / zs + K.cy], axis=-1)
    err = np.where(valid, np.linalg.norm(proj - uv, axis=-1), 0.0)
    ok &= err.max(axis=1) <= cfg.max_reprojection_px
    for row, i in enumerate(idx):
        if ok[row]:
            out[i] = p[row]
    return out
