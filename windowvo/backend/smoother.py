"""Back end: a GTSAM fixed-lag smoother over keyframe poses and landmarks.

States: ``X(k)`` is ``T_world_base`` of keyframe k (a ``Pose3``), ``L(id)`` the world position
of the landmark of track ``id`` (a ``Point3``). The camera enters the projection factors
through ``T_base_cam`` (GTSAM's ``body_P_sensor``).

Key lifecycle (designed so that GTSAM's fixed-lag smoother never meets a key it cannot
handle, see GTSAM issues #1638/#1795/#2478):

* the smoother's clock is the keyframe counter; the lag is ``window_keyframes - 1``;
* every new pose arrives with its timestamp and at least one factor (odometry between-factor,
  or a weak motion prior in monocular mode); every new landmark with its timestamp and at
  least two projection factors, all on poses still inside the window;
* a landmark's timestamp is refreshed whenever a new keyframe observes it, so it is
  marginalised together with the last pose that saw it;
* every landmark is born with a weak position prior (sigma about its depth), so a landmark
  whose projection factors are removed as outliers, or lose their Jacobians when the point
  falls behind a camera, is never left undetermined;
* any remaining failure (indeterminant system, cheirality) resets the window from the last
  good pose with a prior and falls back on wheel odometry for that keyframe.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import gtsam
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, RobustKind
from ..geometry import inv_T
from ..types import BackendOutput, BackendStatus, FrontendOutput, GateOutcome

log = logging.getLogger(__name__)


def X(k: int) -> int:
    return gtsam.symbol("x", k)


def L(track_id: int) -> int:
    return gtsam.symbol("l", track_id)


@dataclass
class LandmarkState:
    key: int
    last_kf: int
    factor_indices: list[tuple[int, int]] = field(default_factory=list)  # (keyframe, factor index)
    strikes: int = 0


@dataclass
class OdometryStep:
    """Wheel odometry between the previous keyframe and this one."""

    T_prev_cur: np.ndarray  # T_base(k-1)_base(k)
    distance_m: float
    ok: bool = True  # False when odometry was missing or stale for this step


def odometry_noise(cfg: BackendConfig, distance: float, yaw: float):
    """Noise of a wheel-odometry step, as two parts of one between-measurement.

    The planar part (x, y, yaw) is what wheels measure: tight, growing with distance, under
    the configured robust loss so that vision can overrule slip. The vertical part (z, roll,
    pitch) only says "the robot drives on its wheels": loose and plain Gaussian, so it keeps
    linking the window even where vision is briefly lost (a robust loss would let that link go).
    Each part leaves the other's components free (sigma 1e3), so together they carry the
    information of one anisotropic factor.
    """
    o = cfg.odometry
    free = 1e3
    s_xy = max(o.xy_sigma_min_m, o.xy_sigma_per_m * distance)
    s_yaw = max(o.yaw_sigma_min_rad, o.yaw_sigma_per_m * distance + 0.02 * abs(yaw))
    planar = gtsam.noiseModel.Diagonal.Sigmas(np.array([free, free, s_yaw, s_xy, s_xy, free]))
    vertical = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([o.roll_pitch_sigma_rad, o.roll_pitch_sigma_rad, free, free, free, o.z_sigma_m]))
    return robust(planar, o.robust, o.robust_k), vertical


def robust(base, kind: RobustKind, k: float):
    """Wrap a Gaussian noise model in the configured M-estimator (threshold k in sigmas)."""
    if kind is RobustKind.HUBER:
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind is RobustKind.CAUCHY:
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base


class SlidingWindowBackend:
    """Fixed-lag smoother fed one keyframe at a time."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, use_odometry: bool):
        self.camera = camera
        self.cfg = cfg
        self.use_odometry = use_odometry
        self.K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        self.T_base_cam = camera.T_base_cam
        self.body_P_sensor = gtsam.Pose3(camera.T_base_cam)
        self.pixel_noise = robust(gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma), cfg.robust, cfg.huber_k)
        self.lag = float(cfg.window_keyframes - 1)
        self._cos_min_angle = float(np.cos(np.radians(cfg.min_triangulation_angle_deg)))
        self.k = -1
        self.kf_frame: dict[int, int] = {}
        self.kf_time: dict[int, float] = {}
        self.kf_pose: dict[int, np.ndarray] = {}  # latest estimate; final once marginalised
        self.obs: dict[int, list[tuple[int, np.ndarray]]] = {}  # track id -> [(k, undistorted px)]
        self.landmarks: dict[int, LandmarkState] = {}
        self.dead: set[int] = set()
        self.pending_removal: list[int] = []
        self.estimate: gtsam.Values | None = None
        self.n_resets = 0
        self._new_smoother()

    # ------------------------------------------------------------------ smoother plumbing
    def _new_smoother(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.cfg.relinearize_threshold)
        params.relinearizeSkip = self.cfg.relinearize_skip
        # Reuse the slots of removed and marginalised factors: otherwise the factor list grows by
        # every factor ever added, and memory and update time with it.
        params.findUnusedFactorSlots = True
        if self.cfg.optimizer == "dogleg":
            # Powell's dogleg keeps iSAM2's steps inside a trust region: far landmarks with little
            # parallax make plain Gauss-Newton overshoot.
            params.setOptimizationParams(gtsam.ISAM2DoglegParams())
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag, params)

    def window_start(self, k: int | None = None) -> int:
        """Oldest keyframe index still (and after this update, still) in the window."""
        k = self.k if k is None else k
        return max(0, k - (self.cfg.window_keyframes - 1))

    def pose(self, k: int) -> np.ndarray:
        return self.kf_pose[k]

    # ------------------------------------------------------------------ main entry
    def add_keyframe(self, fo: FrontendOutput, odom: OdometryStep | None) -> BackendOutput:
        t0 = time.perf_counter()
        self.k += 1
        k = self.k
        self.kf_frame[k] = fo.frame_index
        self.kf_time[k] = fo.timestamp
        status = BackendStatus.OK
        use_vision = fo.vision_ok
        # New landmarks need a vision-worthy keyframe; each one is still checked for its own
        # triangulation angle, so low overall parallax (distant scenes) does not block it.
        allow_new = fo.gate in (GateOutcome.PASS, GateOutcome.LOW_PARALLAX) or k == 1
        T_guess = self._initial_guess(fo, odom)
        try:
            n_new, n_vis = self._update(fo, odom, T_guess, use_vision, allow_new)
            if k == 0:
                status = BackendStatus.INIT
            elif not use_vision:
                status = BackendStatus.ODOMETRY_FALLBACK
        except RuntimeError as err:
            msg = " ".join(str(err).split())[:300]
            log.warning("keyframe %d (frame %d): smoother failed (%s); resetting the window from the last good pose",
                        k, fo.frame_index, msg)
            self._reset_with(fo, odom, T_guess)
            n_new, n_vis = 0, 0
            status = BackendStatus.RECOVERED
        out = self._output(fo, n_new, n_vis, status)
        out.backend_ms = (time.perf_counter() - t0) * 1000.0
        return out

    # ------------------------------------------------------------------ pieces
    def _initial_guess(self, fo: FrontendOutput, odom: OdometryStep | None) -> np.ndarray:
        k = self.k
        if k == 0:
            return np.eye(4)
        T_prev = self.kf_pose[k - 1]
        if odom is not None and odom.ok and self.use_odometry:
            return T_prev @ odom.T_prev_cur
        T_pnp = self._pnp(fo)
        if T_pnp is not None:
            return T_pnp
        if k == 1 and fo.R_cam_kf_cam is not None and fo.t_dir_kf is not None:
            # Two-view initialisation with a unit baseline: X_cur = R X_kf + t.
            T_cur_kf = np.eye(4)
            T_cur_kf[:3, :3] = fo.R_cam_kf_cam
            T_cur_kf[:3, 3] = fo.t_dir_kf / max(np.linalg.norm(fo.t_dir_kf), 1e-9)
            T_world_cam = T_prev @ self.T_base_cam @ inv_T(T_cur_kf)
            return T_world_cam @ inv_T(self.T_base_cam)
        if k >= 2:  # constant velocity
            d = inv_T(self.kf_pose[k - 2]) @ T_prev
            return T_prev @ d
        return T_prev.copy()

    def _pnp(self, fo: FrontendOutput) -> np.ndarray | None:
        if self.estimate is None:
            return None
        pts3, pts2 = [], []
        for tid, uv in zip(fo.track_ids.tolist(), fo.pixels_undistorted):
            lm = self.landmarks.get(tid)
            if lm is not None and self.estimate.exists(lm.key):
                pts3.append(self.estimate.atPoint3(lm.key))
                pts2.append(uv)
        if len(pts3) < 12:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            np.asarray(pts3, np.float64), np.asarray(pts2, np.float64), self.camera.K, None,
            reprojectionError=2.0 * self.cfg.pixel_sigma + 1.0, iterationsCount=100, flags=cv2.SOLVEPNP_EPNP
        )
        if not ok or inl is None or len(inl) < 10:
            return None
        R, _ = cv2.Rodrigues(rvec)
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = R
        T_cam_world[:3, 3] = tvec.ravel()
        return inv_T(T_cam_world) @ inv_T(self.T_base_cam)

    def _motion_factors(self, graph, k: int, odom: OdometryStep | None, fo: FrontendOutput, T_guess) -> None:
        cfg = self.cfg
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
            return
        if odom is not None and odom.ok and self.use_odometry:
            yaw = float(np.arctan2(odom.T_prev_cur[1, 0], odom.T_prev_cur[0, 0]))
            planar_noise, vertical_noise = odometry_noise(cfg, odom.distance_m, yaw)
            meas = gtsam.Pose3(odom.T_prev_cur)
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), meas, planar_noise))
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), meas, vertical_noise))
            return
        # Monocular (or odometry missing for this step).
        delta = inv_T(self.kf_pose[k - 1]) @ T_guess
        if k == 1 and not self.use_odometry:
            # Gauge for scale: the first baseline has unit length.
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.1, 0.02, 0.02, 0.02]))
        else:
            # A weak motion prior only keeps the system determined when vision is thin.
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5, 0.5, 0.5, 5.0, 5.0, 5.0]))
        graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(delta), noise))

    def _planar_factors(self, graph, k: int, T_guess: np.ndarray) -> None:
        pp = self.cfg.planar_prior
        if not pp.enabled or k == 0:
            return
        base = gtsam.noiseModel.Isotropic.Sigma(2, pp.sigma_rad)
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(pp.huber_k), base)
        up = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
        graph.add(gtsam.AttitudeFactorPose3(X(k), up, noise, up))
        if pp.height_prior:
            sig = np.array([1e3, 1e3, 1e3, 1e3, 1e3, pp.height_sigma_m])
            R = T_guess[:3, :3]
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(gtsam.Rot3(R), np.array([T_guess[0, 3], T_guess[1, 3], 0.0])),
                                             gtsam.noiseModel.Diagonal.Sigmas(sig)))

    def _proj(self, uv: np.ndarray, k: int, key: int):
        return gtsam.GenericProjectionFactorCal3_S2(np.asarray(uv, float), self.pixel_noise, X(k), key, self.K,
                                                    self.body_P_sensor)

    def _camera_poses(self, poses: dict[int, np.ndarray]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """T_world_cam rotation and centre per keyframe, computed once per update."""
        out = {}
        for kk, T in poses.items():
            T_wc = T @ self.T_base_cam
            out[kk] = (T_wc[:3, :3], T_wc[:3, 3])
        return out

    def _try_triangulate(self, tid: int, cams: dict[int, tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
        """Midpoint triangulation of a track over the window, with angle, depth and reprojection checks."""
        cfg = self.cfg
        obs = [(kk, uv) for kk, uv in self.obs.get(tid, []) if kk in cams]
        if len(obs) < 2:
            return None
        K = self.camera
        # Cheap test first: the rays of the first and last observation must already diverge.
        (k_a, uv_a), (k_b, uv_b) = obs[0], obs[-1]
        ra = cams[k_a][0] @ np.array([(uv_a[0] - K.cx) / K.fx, (uv_a[1] - K.cy) / K.fy, 1.0])
        rb = cams[k_b][0] @ np.array([(uv_b[0] - K.cx) / K.fx, (uv_b[1] - K.cy) / K.fy, 1.0])
        if np.dot(ra, rb) / np.sqrt(np.dot(ra, ra) * np.dot(rb, rb)) > self._cos_min_angle:
            return None
        uv = np.asarray([o[1] for o in obs])
        R = np.stack([cams[kk][0] for kk, _ in obs])  # (n, 3, 3) R_world_cam
        c = np.stack([cams[kk][1] for kk, _ in obs])  # (n, 3) camera centres
        rays_c = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(obs))], axis=1)
        d = np.einsum("nij,nj->ni", R, rays_c)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        if np.degrees(np.arccos(np.clip(np.min(d @ d.T), -1, 1))) < cfg.min_triangulation_angle_deg:
            return None
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        A = P.sum(axis=0)
        b = np.einsum("nij,nj->i", P, c)
        if np.linalg.det(A) < 1e-9:
            return None
        p = np.linalg.solve(A, b)
        pc = np.einsum("nji,nj->ni", R, p[None, :] - c)  # R^T (p - c)
        z = pc[:, 2]
        if np.any(z <= 0.1) or np.any(z > cfg.max_landmark_depth_m):
            return None
        proj = np.stack([K.fx * pc[:, 0] / z + K.cx, K.fy * pc[:, 1] / z + K.cy], axis=1)
        if np.max(np.linalg.norm(proj - uv, axis=1)) > cfg.max_reprojection_px:
            return None
        return p

    def _update(self, fo: FrontendOutput, odom, T_guess, use_vision: bool, allow_new: bool) -> tuple[int, int]:
        k = self.k
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        values.insert(X(k), gtsam.Pose3(T_guess))
        stamps[X(k)] = float(k)
        self._motion_factors(graph, k, odom, fo, T_guess)
        self._planar_factors(graph, k, T_guess)
        # Outlier landmarks flagged after the previous update: remove their factors, keep the
        # key alive with a weak prior until it is marginalised.
        remove = list(self.pending_removal)
        self.pending_removal = []
        owners: list[tuple[int, int] | None] = [None] * graph.size()  # (track id, keyframe) per factor
        w0 = self.window_start(k)
        n_vis = 0
        new_lms: list[int] = []
        candidates: list[int] = []
        cam_center = (T_guess @ self.T_base_cam)[:3, 3]
        if use_vision:
            poses = {kk: self.kf_pose[kk] for kk in range(w0, k)}
            poses[k] = T_guess
            cams = self._camera_poses(poses)
            for tid, uv in zip(fo.track_ids.tolist(), fo.pixels_undistorted):
                if tid in self.dead:
                    continue
                lm = self.landmarks.get(tid)
                if lm is not None:
                    graph.add(self._proj(uv, k, lm.key))
                    owners.append((tid, k))
                    stamps[lm.key] = float(k)
                    lm.last_kf = k
                    n_vis += 1
                    continue
                lst = self.obs.setdefault(tid, [])
                lst.append((k, np.asarray(uv, float)))
                if allow_new and len(lst) >= self.cfg.min_landmark_observations:
                    candidates.append(tid)
            # New landmarks, longest tracks first, up to the landmark budget of the window.
            budget = self.cfg.max_landmarks - len(self.landmarks)
            candidates.sort(key=lambda t: -len(self.obs[t]))
            for tid in candidates:
                if budget <= 0:
                    break
                lst = self.obs[tid]
                p = self._try_triangulate(tid, cams)
                if p is None:
                    continue
                key = L(tid)
                values.insert(key, gtsam.Point3(p))
                stamps[key] = float(k)
                # A weak prior (sigma ~ depth) keeps the landmark determined even if its
                # projection factors lose their Jacobians (point behind a camera) or are
                # removed as outliers; it is negligible next to real observations.
                depth = float(np.linalg.norm(p - cam_center))
                graph.add(gtsam.PriorFactorPoint3(key, p, gtsam.noiseModel.Isotropic.Sigma(3, max(1.0, depth))))
                owners.append(None)
                for kk, uv_k in lst:
                    if kk >= w0:
                        graph.add(self._proj(uv_k, kk, key))
                        owners.append((tid, kk))
                        n_vis += 1
                self.landmarks[tid] = LandmarkState(key, k)
                new_lms.append(tid)
                del self.obs[tid]
                budget -= 1
        ts_map = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t in stamps.items():
            ts_map.insert((key, t))
        try:
            idx = self._submit(graph, values, ts_map, remove)
            for _ in range(self.cfg.extra_iterations if k > 2 else 2):
                self.smoother.update()  # more Gauss-Newton steps (iSAM2 takes one per update)
            self.estimate = self.smoother.calculateEstimate()
        except RuntimeError:
            # Undo the bookkeeping of this update before the caller resets the window.
            for tid in new_lms:
                self.landmarks.pop(tid, None)
                self.dead.add(tid)
            raise
        for fi, owner in zip(idx, owners):
            if owner is not None and owner[0] in self.landmarks:
                self.landmarks[owner[0]].factor_indices.append((owner[1], int(fi)))
        self._refresh_poses()
        self._prune(k)
        self._check_outliers(fo)
        return len(new_lms), n_vis

    def _submit(self, graph, values, ts_map, remove) -> list[int]:
        """One smoother update; returns the smoother's indices of the new factors."""
        self.smoother.update(graph, values, ts_map, remove)
        return list(self.smoother.getISAM2Result().getNewFactorsIndices())

    def _refresh_poses(self) -> None:
        est = self.estimate
        for kk in range(self.window_start(), self.k + 1):
            if est.exists(X(kk)):
                self.kf_pose[kk] = est.atPose3(X(kk)).matrix()

    def _prune(self, k: int) -> None:
        """Forget bookkeeping of keys the smoother has marginalised."""
        w0 = self.window_start(k)
        for tid in [t for t, lm in self.landmarks.items() if lm.last_kf < w0]:
            del self.landmarks[tid]
            self.dead.add(tid)
        for tid in list(self.obs):
            kept = [(kk, uv) for kk, uv in self.obs[tid] if kk >= w0]
            if kept:
                self.obs[tid] = kept
            else:
                del self.obs[tid]
        # Dead ids only matter while their tracks may still be alive in the front end.
        if len(self.dead) > 50_000:
            self.dead = set(sorted(self.dead)[-20_000:])

    def _check_outliers(self, fo: FrontendOutput) -> None:
        """Landmarks whose reprojection error stays large on two keyframes are dropped."""
        k = self.k
        T_cw = inv_T(self.kf_pose[k] @ self.T_base_cam)
        for tid, uv in zip(fo.track_ids.tolist(), fo.pixels_undistorted):
            lm = self.landmarks.get(tid)
            if lm is None or lm.last_kf != k or not self.estimate.exists(lm.key):
                continue
            p = self.estimate.atPoint3(lm.key)
            pc = T_cw[:3, :3] @ p + T_cw[:3, 3]
            err = np.inf if pc[2] <= 0.05 else np.hypot(*(self.camera.K @ (pc / pc[2]))[:2] - uv)
            if err > self.cfg.outlier_residual_px:
                lm.strikes += 1
                if lm.strikes >= 2:
                    # Factors on marginalised poses are already gone from the smoother.
                    w_next = self.window_start(k + 1)
                    self.pending_removal.extend(fi for kk, fi in lm.factor_indices if kk >= w_next)
                    del self.landmarks[tid]
                    self.dead.add(tid)
            else:
                lm.strikes = 0

    def _reset_with(self, fo: FrontendOutput, odom, T_guess: np.ndarray) -> None:
        """Start a fresh window from the last good pose; this keyframe rests on odometry."""
        k = self.k
        self.n_resets += 1
        self._new_smoother()
        for tid in list(self.landmarks):
            self.dead.add(tid)
        self.landmarks.clear()
        self.obs.clear()
        self.pending_removal = []
        T_prev = self.kf_pose.get(k - 1, np.eye(4))
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        ts_map = gtsam.FixedLagSmootherKeyTimestampMap()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
        else:
            prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.01, 0.02, 0.02, 0.02]))
            graph.add(gtsam.PriorFactorPose3(X(k - 1), gtsam.Pose3(T_prev), prior))
            values.insert(X(k - 1), gtsam.Pose3(T_prev))
            ts_map.insert((X(k - 1), float(k - 1)))
            self._motion_factors(graph, k, odom, fo, T_guess)
        values.insert(X(k), gtsam.Pose3(T_guess))
        ts_map.insert((X(k), float(k)))
        self.smoother.update(graph, values, ts_map)
        self.estimate = self.smoother.calculateEstimate()
        self.kf_pose[k] = self.estimate.atPose3(X(k)).matrix()
        if k > 0:
            self.kf_pose[k - 1] = self.estimate.atPose3(X(k - 1)).matrix()
        # Observations of this keyframe seed new landmarks once the next keyframe arrives.
        for tid, uv in zip(fo.track_ids.tolist(), fo.pixels_undistorted):
            self.obs[tid] = [(k, np.asarray(uv, float))]
        self.dead.difference_update(fo.track_ids.tolist())

    def _output(self, fo: FrontendOutput, n_new: int, n_vis: int, status: BackendStatus) -> BackendOutput:
        est = self.estimate
        ids, pts = [], []
        for tid, lm in self.landmarks.items():
            if est.exists(lm.key):
                ids.append(tid)
                pts.append(est.atPoint3(lm.key))
        # Reprojection RMS over this keyframe's observations of landmarks.
        T_cw = inv_T(self.kf_pose[self.k] @ self.T_base_cam)
        errs = []
        for tid, uv in zip(fo.track_ids.tolist(), fo.pixels_undistorted):
            lm = self.landmarks.get(tid)
            if lm is None or lm.last_kf != self.k or not est.exists(lm.key):
                continue
            pc = T_cw[:3, :3] @ est.atPoint3(lm.key) + T_cw[:3, 3]
            if pc[2] > 0.05:
                pr = self.camera.K @ (pc / pc[2])
                errs.append(np.hypot(pr[0] - uv[0], pr[1] - uv[1]))
        rms = float(np.sqrt(np.mean(np.square(np.minimum(errs, 50.0))))) if errs else float("nan")
        w0 = self.window_start()
        return BackendOutput(
            frame_index=fo.frame_index,
            timestamp=fo.timestamp,
            T_world_base=self.kf_pose[self.k].copy(),
            keyframe_poses={self.kf_frame[kk]: self.kf_pose[kk] for kk in range(w0, self.k + 1)},
            p_world_landmarks=np.asarray(pts).reshape(-1, 3),
            landmark_ids=np.asarray(ids, np.int64),
            n_landmarks=len(ids),
            n_new_landmarks=n_new,
            n_vision_factors=n_vis,
            reprojection_rms_px=rms,
            status=status,
        )
