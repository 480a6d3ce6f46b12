"""The vision part of one back-end update: projection factors and new landmarks (``LandmarkFactors``).

For the keyframe the window (``smoother.py``) is adding, it adds to the update's graph the projection
factors of the known landmarks the keyframe sees (``observation_factors``), and the new landmarks within
the landmark budgets (``new_landmark_factors``): triangulated longest track first, each with its weak
birth prior, its projection factors on the window's keyframes and, on the floor (``FloorModel.floor_of``),
its ground factor (``FloorModel.birth_ground_factor``). The landmarks' bookkeeping is the landmark
manager's (``landmarks.py``); the window owns the keys' timestamps and the smoother.

With ``backend.landmark_model: smart`` the landmarks off the floor are GTSAM smart projection factors
(no point state): one factor per landmark over its observations in the window; a new observation
replaces it (the old slot is removed in the same update, as Kimera-VIO's ``updateLandmarkInGraph``).
Floor landmarks stay explicit: their ground factors need the point ``G(id)``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, LandmarkModel
from ..types import FrontendOutput
from . import factors as fac
from .factors import L, X
from .floor import FloorModel
from .landmarks import LandmarkManager, SmartTrack


def within_budget(born: list[tuple[int, np.ndarray]], on_floor: np.ndarray, budgets: tuple[int, int]
                  ) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
    """Keep floor landmarks within the floor budget and the others within the window's budget (budgets:
    room for (others, floor)); a floor landmark beyond the floor budget is kept as another one."""
    reg_left, floor_left = budgets
    keep = []
    for i, floor in enumerate(on_floor):
        if floor and floor_left > 0:
            floor_left -= 1
            keep.append(i)
        elif reg_left > 0:
            reg_left -= 1
            on_floor[i] = False
            keep.append(i)
    return [born[i] for i in keep], on_floor[keep]


class LandmarkFactors:
    """Projection factors of the window's landmarks and the births of new ones, one keyframe at a time."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, lm: LandmarkManager, floor: FloorModel,
                 kf_pose: dict[int, np.ndarray], K: gtsam.Cal3_S2, body_P_sensor: gtsam.Pose3):
        self.cfg = cfg
        self.lm = lm  # the window's landmarks (shared with the smoother)
        self.floor = floor
        self.kf_pose = kf_pose  # the window's keyframe poses T_world_base (the smoother's; read here)
        self.T_base_cam = camera.T_base_cam
        self.K = K
        self.body_P_sensor = body_P_sensor
        self.pixel_noise = fac.pixel_noise(cfg)
        self.smart = cfg.landmark_model is LandmarkModel.SMART
        self.smart_params = fac.smart_params(cfg) if self.smart else None

    def observation_factors(self, k: int, w0: int, graph, stamps: dict[int, float], owners: list,
                            fo: FrontendOutput, allow_new: bool) -> tuple[int, list[int]]:
        """Projection factors of the landmarks keyframe k sees (``w0`` the window's start; a smart landmark's
        factor is replaced by one with this observation). Returns their number and the tracks that may become
        landmarks now."""
        seen, candidates = self.lm.observe(fo.track_ids, fo.pixels_undistorted, k, allow_new, fo.pixel_sigma_scale,
                                           window_start=w0)
        for tid, uv, sc in seen:
            lm = self.lm.landmarks[tid]
            if lm.smart is not None:
                self.lm.replace_smart(tid)
                self._add_smart(tid, lm.smart, graph, owners)
                continue
            graph.add(fac.projection_factor(uv, X(k), lm.key, self._pixel_noise(sc), self.K, self.body_P_sensor))
            owners.append((tid, k, False))
            stamps[lm.key] = float(k)
        return len(seen), candidates

    def _add_smart(self, tid: int, track: SmartTrack, graph, owners: list) -> None:
        """A smart landmark's factor over all its observations, into the update (owned by its oldest keyframe)."""
        obs = track.observations
        stretch = self._used_stretch(sum(sc for _, _, sc in obs) / len(obs))
        assert self.smart_params is not None
        track.factor = fac.smart_factor([(X(kk), uv) for kk, uv, _ in obs],
                                        self.cfg.pixel_sigma * stretch, self.K, self.body_P_sensor, self.smart_params)
        graph.add(track.factor)
        owners.append((tid, track.first_kf, False))

    def new_landmark_factors(self, k: int, w0: int, graph, values, stamps: dict[int, float], owners: list,
                             candidates: list[int], T_guess: np.ndarray) -> tuple[list[int], int, int]:
        """New landmarks of keyframe k (within the budgets; ``w0`` the window's start): each with its birth
        prior, its projection factors in the window and, on the floor, its ground factor. Returns (their
        track ids, projection factors, ground factors)."""
        floor_model = self.floor
        poses = {kk: self.kf_pose[kk] for kk in range(w0, k)}
        poses[k] = T_guess
        cams = LandmarkManager.camera_poses(poses, self.T_base_cam)
        budgets = self._budgets(k)  # no landmark is born before both uses below
        born = self._triangulate_candidates(candidates, cams, T_guess, budgets)
        on_floor, floor_fit = floor_model.floor_of(k, born, T_guess)
        born, on_floor = within_budget(born, on_floor, budgets)
        up_world = floor_model.level_up(k, w0, T_guess, floor_fit if on_floor.any() else None)
        n_base = floor_model.floor_normal_base()  # the same for all of this keyframe's floor points
        cam_center = (T_guess @ self.T_base_cam)[:3, 3]
        new_lms: list[int] = []
        n_vis = n_ground = 0
        n_floor = int(np.count_nonzero(on_floor))  # the floor points keyframe k ties (they share its floor's error)
        if n_floor and floor_model.ties_allowed():
            floor_model.add_floor_frame(k, graph, values, stamps, owners, T_guess)
        for (tid, p), floor in zip(born, on_floor):
            new_lms.append(tid)
            if self.smart and not floor:
                track = self.lm.promote_smart(tid, k, w0)
                self._add_smart(tid, track, graph, owners)
                n_vis += len(track.observations)
                continue
            key = fac.G(tid) if floor else L(tid)
            values.insert(key, gtsam.Point3(p))
            stamps[key] = float(k)
            graph.add(fac.landmark_birth_prior(key, p, float(np.linalg.norm(p - cam_center))))
            owners.append(None)
            for kk, uv_k, sc in self.lm.promote(tid, k, bool(floor)):
                if kk >= w0:
                    graph.add(fac.projection_factor(uv_k, X(kk), key, self._pixel_noise(sc), self.K,
                                                    self.body_P_sensor))
                    owners.append((tid, kk, False))
                    n_vis += 1
            if floor and floor_model.ties_allowed():
                graph.add(floor_model.birth_ground_factor(k, key, p, T_guess, up_world, n_base, n_floor))
                owners.append((tid, k, up_world is None))
                n_ground += 1
        return new_lms, n_vis, n_ground

    def _pixel_noise(self, stretch: float):
        """Projection noise of one observation: the lens's stretch of the undistortion at that pixel scales
        the sensor's pixel sigma (exactly 1 for a pinhole, up to 1/cos^2 of the ray angle for a fisheye)."""
        stretch = self._used_stretch(stretch)
        return self.pixel_noise if stretch == 1.0 else fac.pixel_noise(self.cfg, stretch)

    def _used_stretch(self, stretch: float) -> float:
        """The lens stretch a projection noise uses: 1 without lens noise propagation or within 5% of 1 (a pinhole)."""
        return 1.0 if not self.cfg.propagate_lens_noise or abs(stretch - 1.0) < 0.05 else stretch

    def _triangulate_candidates(self, candidates: list[int], cams, T_guess: np.ndarray,
                                budgets: tuple[int, int]) -> list[tuple[int, np.ndarray]]:
        """Triangulate tracks, longest first, while the landmark budgets (others, floor) have room.

        Floor landmarks fix the metric scale, so tracks below the horizon have a budget of their own
        (``ground.max_landmarks``) besides the window's ``max_landmarks``."""
        reg_left, floor_left = budgets
        below = self.floor.below_horizon(candidates, T_guess) if floor_left > 0 else np.zeros(len(candidates), bool)
        born: list[tuple[int, np.ndarray]] = []
        # All at once (vectorised); then taken in order while the budgets have room.
        wanted = [tid for tid, is_below in zip(candidates, below) if (floor_left if is_below else reg_left) > 0]
        points = dict(zip(wanted, self.lm.triangulate(wanted, cams)))
        for tid, is_below in zip(candidates, below):
            if reg_left <= 0 and floor_left <= 0:
                break
            if (floor_left if is_below else reg_left) <= 0:
                continue
            p = points[tid]
            if p is None:
                continue
            born.append((tid, p))
            if is_below:
                floor_left -= 1
            else:
                reg_left -= 1
        return born

    def _budgets(self, k: int) -> tuple[int, int]:
        """Room for new landmarks at keyframe k: (others, floor). Landmarks count against the budgets while a
        keyframe among the last ``window_keyframes + 1`` saw them: with ``marginalize_every`` 1 that is
        every landmark the smoother holds during an update; with blocks, those waiting for their block
        to leave do not take new ones' places. A monocular run still waiting for the floor
        (``FloorModel.waiting_for_floor``) keeps the floor's budget for tracks below the horizon, so the
        floor, once in view, is in the window. With ``min_landmarks_in_view``, the others' room is at least what
        brings the landmarks keyframe k-1 saw up to that many (a budget held by ended tracks still admits new ones)."""
        lag = self.cfg.budget_lag(self.floor.use_odometry)
        return self.lm.budgets(self.cfg.ground.max_landmarks if self.floor.use_ground else 0, k - lag, k - 1)
