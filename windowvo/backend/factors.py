"""Factor builders of the back end: one small function per factor, one concern each.

Pure functions: they take measurements, keys and noise settings and return GTSAM factors;
they never touch the smoother. Keys: ``X(k)`` is ``T_world_base`` of keyframe k (``Pose3``),
``L(id)`` the world position of the landmark of track ``id`` (``Point3``; ``G(id)`` for a floor
landmark, so that iSAM2 can relinearise the two kinds at their own thresholds,
:func:`relinearize_thresholds`), ``C(k)`` the wheel calibration from keyframe k on (``Point3``:
distance scale, yaw bias in rad per metre, yaw scale).

Robust losses: GTSAM applies an M-estimator to the norm of the whitened residual, whose
square is chi-square distributed with the factor's dimension. :func:`robust_threshold` turns a
confidence (``backend.robust_confidence``) into the threshold for a factor of dimension d,
so a 2-D pixel, a 3-D planar odometry and the ground residual are judged alike (the ground factor is
a bearing weighted on its elevation only, its azimuth nearly free: effectively 1-D, judged as such;
its variant for a rocking base, :func:`level_ground_factor`, is 1-D outright).
"""

from __future__ import annotations

import math
from functools import lru_cache, partial

import gtsam
import numpy as np

from ..config import BackendConfig, RobustKind
from .chi2 import chi2_quantile

# A sigma that leaves a component of a Pose3 factor effectively free.
FREE_SIGMA = 1e3
# Yaw uncertainty added per radian of turn in one odometry step (wheel geometry errors grow with turning).
YAW_SIGMA_PER_RAD = 0.02
# Wheel steps shorter than this are not tied by their climb rate (standing still: the rate is undefined).
CLIMB_MIN_STEP_M = 0.02
# Smart projection factors: re-triangulate when a pose moved this much (Kimera-VIO's setting), and the rank
# tolerance of their triangulation.
SMART_RETRIANGULATION_THRESHOLD = 1e-3
SMART_RANK_TOLERANCE = 1.0
# Symbols of the smoother's states (each needs a relinearisation threshold, see relinearize_thresholds).
POSE_SYMBOL, LANDMARK_SYMBOL, FLOOR_LANDMARK_SYMBOL, CALIBRATION_SYMBOL = "x", "l", "g", "c"
FLOOR_FRAME_SYMBOL = "f"
FLOOR_DEPTH_SYMBOL = "d"


def X(k: int) -> int:
    """Key of ``T_world_base`` of keyframe k."""
    return gtsam.symbol(POSE_SYMBOL, k)


def L(track_id: int) -> int:
    """Key of ``p_world_landmark`` of track ``track_id``."""
    return gtsam.symbol(LANDMARK_SYMBOL, track_id)


def G(track_id: int) -> int:
    """Key of ``p_world_landmark`` of track ``track_id`` when it is a floor landmark."""
    return gtsam.symbol(FLOOR_LANDMARK_SYMBOL, track_id)


def F(k: int) -> int:
    """Key of keyframe k's floor frame ``T_world_floor`` (``ground.floor_state``): the base pose the floor's
    tilt and height are measured in."""
    return gtsam.symbol(FLOOR_FRAME_SYMBOL, k)


def D(k: int) -> int:
    """Key of the floor's depth below its configured height from keyframe k on (``ground.height_sigma_fraction``):
    metres the true floor lies below the one ``camera_height_m`` puts under the base (a double)."""
    return gtsam.symbol(FLOOR_DEPTH_SYMBOL, k)


def C(k: int) -> int:
    """Key of the wheel calibration (scale, yaw bias per metre) at keyframe k."""
    return gtsam.symbol(CALIBRATION_SYMBOL, k)


# ---------------------------------------------------------------------------- iSAM2 settings


def block_starts(cfg: BackendConfig, k: int) -> bool:
    """Keyframe k starts a block of keyframes that leave the window together (``marginalize_every``): a slowly
    varying state (the wheel calibration ``C``, the floor depth ``D``) takes a new value with each block, not with
    each keyframe (every extra state joins the dense block of poses iSAM2 re-eliminates at each update)."""
    return (k + cfg.window_keyframes - 1) % cfg.marginalize_every == 0


def relinearize_thresholds(cfg: BackendConfig) -> float | gtsam.ISAM2ThresholdMap:
    """iSAM2's relinearisation threshold, one for all states or one per kind of state.

    Landmarks off the floor may have their own threshold in metres: most of an update's work is
    re-eliminating the landmarks a new keyframe sees, and those are mostly metres away, where a few
    centimetres change a projection by a fraction of a pixel. Floor landmarks (near, and their heights
    carry the scale) keep the poses' threshold: relaxing theirs too made a ramp 1.4x worse. A map must
    name every symbol in the graph."""
    t = cfg.relinearize_threshold
    if cfg.landmark_relinearize_threshold_m is None:
        return t
    m = gtsam.ISAM2ThresholdMap()
    for sym, dim, value in ((POSE_SYMBOL, 6, t), (CALIBRATION_SYMBOL, 3, t), (FLOOR_LANDMARK_SYMBOL, 3, t),
                            (FLOOR_FRAME_SYMBOL, 6, t), (FLOOR_DEPTH_SYMBOL, 1, t),
                            (LANDMARK_SYMBOL, 3, cfg.landmark_relinearize_threshold_m)):
        m.insert((sym, np.full(dim, value)))
    return m


# ---------------------------------------------------------------------------- robust losses


@lru_cache(maxsize=64)
def robust_threshold(dim: int, confidence: float) -> float:
    """Threshold (in sigmas of the whitened residual norm) below which a residual of dimension
    ``dim`` is an inlier with probability ``confidence``: sqrt of the chi-square quantile
    (:func:`~windowvo.backend.chi2.chi2_quantile`, without scipy: see its module)."""
    return float(math.sqrt(chi2_quantile(dim, confidence)))


def robust(base, kind: RobustKind, k: float):
    """Wrap a Gaussian noise model in an M-estimator with threshold k (in sigmas)."""
    if kind is RobustKind.HUBER:
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind is RobustKind.CAUCHY:
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base


def threshold(explicit: float | None, dim: int, cfg: BackendConfig) -> float:
    """An explicitly configured threshold wins; otherwise the chi-square one for ``dim``."""
    return float(explicit) if explicit is not None else robust_threshold(dim, cfg.robust_confidence)


# ---------------------------------------------------------------------------- priors


def first_pose_prior(key: int, T_world_base: np.ndarray, sigma: float = 1e-4):
    """Fixes the gauge: the first pose (or the pose a reset restarts from)."""
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(T_world_base), gtsam.noiseModel.Isotropic.Sigma(6, sigma))


def reset_prior(key: int, T_world_base: np.ndarray, cfg: BackendConfig):
    """Holds the last good pose when the window restarts after a failure."""
    r = cfg.reset_prior
    sig = np.array([r.rotation_sigma_rad] * 3 + [r.position_sigma_m] * 3)
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(T_world_base), gtsam.noiseModel.Diagonal.Sigmas(sig))


def landmark_birth_prior(key: int, p_world_landmark: np.ndarray, depth_m: float):
    """A weak prior (sigma about the depth) that keeps a landmark determined if its projection
    factors lose their Jacobians (point behind a camera) or are removed as outliers."""
    return gtsam.PriorFactorPoint3(key, p_world_landmark, gtsam.noiseModel.Isotropic.Sigma(3, max(1.0, depth_m)))


# ---------------------------------------------------------------------------- vision


def pixel_noise(cfg: BackendConfig, stretch: float = 1.0):
    """Robust 2-D pixel noise; ``stretch`` scales the sigma (a lens's undistortion at that pixel)."""
    return robust(gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma * stretch), cfg.robust,
                  threshold(cfg.huber_k, 2, cfg))


def projection_factor(uv: np.ndarray, pose_key: int, landmark_key: int, noise, K: gtsam.Cal3_S2,
                      body_P_sensor: gtsam.Pose3):
    """Reprojection of a landmark into the camera of a keyframe (undistorted pixels, pinhole K)."""
    return gtsam.GenericProjectionFactorCal3_S2(np.asarray(uv, float), noise, pose_key, landmark_key, K, body_P_sensor)


def smart_params(cfg: BackendConfig) -> gtsam.SmartProjectionParams:
    """Settings of the smart projection factors (``backend.landmark_model: smart``), as Kimera-VIO's: a Hessian
    on the poses, zero (no information) when the point cannot be triangulated or falls behind a camera, and the
    landmark dropped when it lies further than ``max_landmark_depth_m`` or an observation reprojects beyond
    ``outlier_residual_px`` (a smart factor takes no robust loss)."""
    p = gtsam.SmartProjectionParams(gtsam.LinearizationMode.HESSIAN, gtsam.DegeneracyMode.ZERO_ON_DEGENERACY,
                                    False, False, SMART_RETRIANGULATION_THRESHOLD)
    p.setRankTolerance(SMART_RANK_TOLERANCE)
    p.setLandmarkDistanceThreshold(cfg.max_landmark_depth_m)
    p.setDynamicOutlierRejectionThreshold(cfg.outlier_residual_px)
    p.setEnableEPI(False)
    return p


@lru_cache(maxsize=64)
def smart_pixel_noise(sigma_px: float):
    """Isotropic Gaussian pixel noise of a smart factor (GTSAM's smart factors take no robust loss); one per sigma."""
    return gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)


def smart_factor(observations: list[tuple[int, np.ndarray]], sigma_px: float, K: gtsam.Cal3_S2,
                 body_P_sensor: gtsam.Pose3, params: gtsam.SmartProjectionParams):
    """One landmark's smart projection factor over its observations (pose key, undistorted pixel): the
    point is triangulated from the poses and eliminated, so the factor connects the poses only."""
    f = gtsam.SmartProjectionPoseFactorCal3_S2(smart_pixel_noise(sigma_px), K, body_P_sensor, params)
    for pose_key, uv in observations:
        f.add(np.asarray(uv, float), pose_key)
    return f


# ---------------------------------------------------------------------------- planar motion


def planar_attitude_factor(key: int, cfg: BackendConfig):
    """Soft, robust roll/pitch prior: the base's z axis points up (yaw and position free)."""
    pp = cfg.planar_prior
    base = gtsam.noiseModel.Isotropic.Sigma(2, pp.sigma_rad)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(pp.huber_k), base)
    up = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
    return gtsam.AttitudeFactorPose3(key, up, noise, up)


def height_prior_factor(key: int, T_guess: np.ndarray, sigma_m: float):
    """Optional soft z = 0 prior on a pose (every other component free)."""
    sig = np.array([FREE_SIGMA] * 5 + [sigma_m])
    prior = gtsam.Pose3(gtsam.Rot3(T_guess[:3, :3]), np.array([T_guess[0, 3], T_guess[1, 3], 0.0]))
    return gtsam.PriorFactorPose3(key, prior, gtsam.noiseModel.Diagonal.Sigmas(sig))


# ---------------------------------------------------------------------------- wheel odometry


def _yaw_and_jacobian(R: np.ndarray) -> tuple[float, np.ndarray]:
    """Yaw of R and its derivative with respect to a right perturbation R Exp(w) (3 columns)."""
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    n = R[0, 0] ** 2 + R[1, 0] ** 2
    # d(R Exp(w))_{i0} = R_i1 w3 - R_i2 w2
    dR00 = np.array([0.0, -R[0, 2], R[0, 1]])
    dR10 = np.array([0.0, -R[1, 2], R[1, 1]])
    return yaw, (R[0, 0] * dR10 - R[1, 0] * dR00) / max(n, 1e-12)


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2.0 * np.pi) - np.pi)


def _calibrated_wheel_error(meas: np.ndarray, distance: float, this: gtsam.CustomFactor, values: gtsam.Values,
                            H: list | None) -> np.ndarray:
    """Residual [yaw, x, y] of a wheel step under a calibration c = (scale, yaw bias per metre, yaw scale).

    The wheels report a planar step ``meas = (x, y, yaw)`` in the base frame of the earlier
    keyframe. With the motion ``D = X(k-1)^-1 X(k)`` they should report ``scale * (D.x, D.y)``
    and ``yaw_scale * D.yaw + bias * distance`` (a differential drive's track width error scales
    every heading change: it is one systematic error of the steps, not noise of each).
    """
    k0, k1, kc = this.keys()
    H1 = np.zeros((6, 6), order="F")
    H2 = np.zeros((6, 6), order="F")
    D = values.atPose3(k0).between(values.atPose3(k1), H1, H2)
    c = values.atPoint3(kc)
    s, b, g = float(c[0]), float(c[1]), float(c[2])
    Dm = D.matrix()
    R, t = Dm[:3, :3], Dm[:3, 3]
    yaw, dyaw_dw = _yaw_and_jacobian(R)
    err = np.array([_wrap(g * yaw + b * distance - meas[2]), s * t[0] - meas[0], s * t[1] - meas[1]])
    if H is not None:
        # d(residual)/d(local perturbation of D): yaw depends on the rotation part, x and y on the
        # translation part through R (GTSAM's Pose3 tangent is [w, v] with t' = t + R v).
        J_D = np.zeros((3, 6))
        J_D[0, :3] = g * dyaw_dw
        J_D[1, 3:] = s * R[0, :]
        J_D[2, 3:] = s * R[1, :]
        H[0] = J_D @ H1
        H[1] = J_D @ H2
        H[2] = np.array([[0.0, distance, yaw], [t[0], 0.0, 0.0], [t[1], 0.0, 0.0]])
    return err


def planar_odometry_sigmas(cfg: BackendConfig, distance: float, yaw: float) -> tuple[float, float]:
    """Sigmas (x/y in metres, yaw in radians) of one wheel step: they grow with distance and turn."""
    o = cfg.odometry
    s_xy = max(o.xy_sigma_min_m, o.xy_sigma_per_m * distance)
    s_yaw = max(o.yaw_sigma_min_rad, o.yaw_sigma_per_m * distance + YAW_SIGMA_PER_RAD * abs(yaw))
    return s_xy, s_yaw


def agrees_with_wheel_step(cfg: BackendConfig, T_wheels: np.ndarray, T_other: np.ndarray, distance: float,
                           step_yaw: float) -> bool:
    """Whether a pose ``T_other`` (PnP's, say) is one the wheel factor would take as an inlier of the wheel step
    (``distance``, turning by ``step_yaw``) that predicts ``T_wheels``: its planar offset (x, y, yaw) within the
    factor's robust threshold in the step's own sigmas, and its tilt against ``T_wheels`` within that many of the
    vertical part's roll/pitch sigma."""
    o = cfg.odometry
    D = np.linalg.solve(T_wheels, T_other)
    yaw = float(np.arctan2(D[1, 0], D[0, 0]))
    s_xy, s_yaw = planar_odometry_sigmas(cfg, distance, step_yaw)
    k = threshold(o.robust_k, 3, cfg)
    planar = np.array([yaw / s_yaw, D[0, 3] / s_xy, D[1, 3] / s_xy])
    tilt = float(np.arccos(np.clip(T_wheels[:3, 2] @ T_other[:3, 2], -1.0, 1.0)))
    return bool(np.linalg.norm(planar) <= k and tilt <= k * o.roll_pitch_sigma_rad)


def odometry_factors(cfg: BackendConfig, k: int, T_prev_cur: np.ndarray, distance: float,
                     calib_key: int | None, heading_only: bool = False) -> list[gtsam.NonlinearFactor]:
    """Wheel odometry between keyframes k-1 and k, as two parts of one measurement.

    The planar part (x, y, yaw) is what wheels measure: tight, growing with distance, under the
    configured robust loss so that vision can overrule slip; with a ``calib_key`` it goes through
    that calibration state (a 3-D custom factor), else a plain between-factor. The vertical
    part (z, roll, pitch) only says "the robot drives on its wheels": loose and Gaussian, so it
    keeps linking the window where vision is briefly lost (a robust loss would let that link go).
    ``heading_only``: the planar part's translation is left free (a step whose distance slipped, ``wheel_slip.py``).
    """
    o = cfg.odometry
    yaw = float(np.arctan2(T_prev_cur[1, 0], T_prev_cur[0, 0]))
    s_xy, s_yaw = planar_odometry_sigmas(cfg, distance, yaw)
    if heading_only:
        s_xy = FREE_SIGMA
    k_planar = threshold(o.robust_k, 3, cfg)
    meas = gtsam.Pose3(T_prev_cur)
    vertical = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([o.roll_pitch_sigma_rad, o.roll_pitch_sigma_rad, FREE_SIGMA, FREE_SIGMA, FREE_SIGMA, o.z_sigma_m]))
    out: list[gtsam.NonlinearFactor] = [gtsam.BetweenFactorPose3(X(k - 1), X(k), meas, vertical)]
    if calib_key is not None:
        noise = robust(gtsam.noiseModel.Diagonal.Sigmas(np.array([s_yaw, s_xy, s_xy])), o.robust, k_planar)
        m = np.array([T_prev_cur[0, 3], T_prev_cur[1, 3], yaw])
        out.append(gtsam.CustomFactor(noise, [X(k - 1), X(k), calib_key],
                                      partial(_calibrated_wheel_error, m, float(distance))))
    else:
        planar = gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA, FREE_SIGMA, s_yaw, s_xy, s_xy, FREE_SIGMA]))
        out.append(gtsam.BetweenFactorPose3(X(k - 1), X(k), meas, robust(planar, o.robust, k_planar)))
    return out


def _climb_change_error(d0: float, d1: float, this: gtsam.CustomFactor, values: gtsam.Values,
                        H: list | None) -> np.ndarray:
    """Residual (m) of the change of climb rate over two consecutive wheel steps k-2 -> k-1 -> k of ``d0``, ``d1``
    metres: ``d (z1 / d1 - z0 / d0)`` with ``d`` their mean and ``z`` each step's translation along its first base
    frame's z axis."""
    k0, k1, k2 = this.keys()
    A0, B0 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    A1, B1 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    D0 = values.atPose3(k0).between(values.atPose3(k1), A0, B0)
    D1 = values.atPose3(k1).between(values.atPose3(k2), A1, B1)
    d = 0.5 * (d0 + d1)
    a0, a1 = d / d0, d / d1
    z0, z1 = float(D0.translation()[2]), float(D1.translation()[2])
    if H is not None:
        # the translation's z under a local perturbation [w, v] of D: t' = t + R v
        J0 = np.zeros((1, 6))
        J0[0, 3:] = D0.rotation().matrix()[2, :]
        J1 = np.zeros((1, 6))
        J1[0, 3:] = D1.rotation().matrix()[2, :]
        H[0] = -a0 * J0 @ A0
        H[1] = -a0 * J0 @ B0 + a1 * J1 @ A1
        H[2] = a1 * J1 @ B1
    return np.array([a1 * z1 - a0 * z0])


def climb_change_factor(cfg: BackendConfig, k: int, d0: float, d1: float) -> gtsam.CustomFactor:
    """The wheel steps k-2 -> k-1 (``d0`` m) and k-1 -> k (``d1`` m) climb at the same rate, to
    ``odometry.climb_sigma_per_m`` of their mean distance (at least ``climb_sigma_min_m``): the base drives on its
    wheels along a floor whose slope changes slowly, whatever the constant tilt of T_base_cam's mount against it."""
    o = cfg.odometry
    sigma = max(o.climb_sigma_min_m, o.climb_sigma_per_m * 0.5 * (d0 + d1))
    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), [X(k - 2), X(k - 1), X(k)],
                              partial(_climb_change_error, float(d0), float(d1)))


def wheel_step_sigmas(cfg: BackendConfig, planar_factor: gtsam.NoiseModelFactor, values: gtsam.Values,
                      T_prev_cur: np.ndarray, distance: float, calibrated: bool) -> np.ndarray:
    """How far the poses (and calibration) in ``values`` lie off a wheel step's planar factor (the last of
    ``odometry_factors``): its planar residual (yaw, x, y) in the step's own sigmas, before any robust loss.
    ``calibrated``: the factor goes through a calibration state (a 3-D residual), else it is a between-factor (a
    6-D one, rotation then translation, whose yaw, x and y are taken)."""
    err = np.array(planar_factor.unwhitenedError(values), dtype=np.float64)
    if not calibrated:
        err = err[[2, 3, 4]]
    yaw = float(np.arctan2(T_prev_cur[1, 0], T_prev_cur[0, 0]))
    s_xy, s_yaw = planar_odometry_sigmas(cfg, distance, yaw)
    return err / np.array([s_yaw, s_xy, s_xy])


def calibration_prior(k: int, calib: np.ndarray, sigmas: np.ndarray):
    """Prior on the wheel calibration (scale, yaw bias per metre, yaw scale) with its three sigmas: the
    initial belief, or what a reset carries over."""
    return gtsam.PriorFactorPoint3(C(k), np.asarray(calib, dtype=float),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=float)))


def calibration_random_walk(cfg: BackendConfig, k_prev: int, k: int, distance: float):
    """The calibration drifts slowly: a random walk from ``C(k_prev)`` to ``C(k)`` whose sigma grows
    with the square root of the distance driven between them."""
    wc = cfg.wheel_calibration
    d = np.sqrt(max(distance, 1e-3))
    sig = np.array([wc.scale_walk_per_sqrt_m * d, wc.yaw_bias_walk_per_sqrt_m * d, wc.yaw_scale_walk_per_sqrt_m * d])
    return gtsam.BetweenFactorPoint3(C(k_prev), C(k), np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(sig))


def monocular_motion_factor(k: int, T_prev_cur: np.ndarray, first_baseline: bool):
    """Without wheels: the first step fixes the gauge of scale (its length, weakly), later steps
    only carry a weak motion prior that keeps the system determined when vision is thin."""
    sig = [0.1, 0.1, 0.1, 0.02, 0.02, 0.02] if first_baseline else [0.5, 0.5, 0.5, 5.0, 5.0, 5.0]
    return gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(T_prev_cur),
                                    gtsam.noiseModel.Diagonal.Sigmas(np.array(sig)))


# ---------------------------------------------------------------------------- ground plane

GROUND_AZIMUTH_SIGMA_RAD = 1.0  # the ground factor's azimuth: left to the projection factors


def ground_factor(pose_key: int, landmark_key: int, p_base: np.ndarray, floor_z: float, sigma_m: float,
                  cfg: BackendConfig, normal_base: np.ndarray | None = None, outlier_sigma_m: float | None = None):
    """Ties a floor landmark to the ground plane of the keyframe that observes it.

    Seen from the base origin (on the floor), a floor point lies on the horizon of the base frame: its
    bearing has elevation ``atan2(floor_z, r)`` at horizontal distance ``r`` (``floor_z`` is 0 unless the
    configured camera height differs from ``T_base_cam``). The factor is GTSAM's native bearing factor
    from the keyframe's pose to the point, weighted on the elevation only: a height error ``dz`` is an
    elevation error ``dz / r``, so the elevation sigma is ``sigma_m / r`` and the whitened residual is the
    point's height off the floor in sigmas. It depends on the pose's roll and pitch, so the floor points
    also hold the base's attitude (a chassis rocking on its suspension). The azimuth gets a loose
    1 rad sigma (the projection factors fix it). Native C++: a Python ``CustomFactor`` cost about 4 ms of
    a 15 ms update in callbacks. Robust, chi-square threshold of 1-D.

    ``normal_base``: the floor's normal in the base frame when it is not the base z axis (a camera mount
    pitched or rolled against ``T_base_cam``, see ``ground.FloorAttitude``); the floor is then the plane
    ``normal_base . q = floor_z`` and heights and elevations are measured along that normal. With the z
    axis the factor is the same bit for bit.

    ``outlier_sigma_m``: the height sigma the robust loss's threshold is counted in (default ``sigma_m``).
    A floor point whose ``sigma_m`` is widened by the error it shares with its keyframe's other floor points
    (``FloorModel.point_sigma_m``) stays an outlier at the same height off the floor.
    """
    n = np.array([0.0, 0.0, 1.0]) if normal_base is None else np.asarray(normal_base, float) / np.linalg.norm(normal_base)
    p = np.asarray(p_base, float)
    q = p - (n @ p - floor_z) * n  # the point moved along n onto the floor {q : n . q = floor_z}
    r = float(np.linalg.norm(q - (n @ q) * n))  # its distance from the base origin along the floor
    if r < 1e-3:
        raise ValueError("a floor point must lie away from the base origin")
    measured = gtsam.Unit3(q)
    B = measured.basis()  # 3 x 2: the tangent plane of the measured bearing
    e = B.T @ n
    s_e = float(np.linalg.norm(e))
    e /= s_e  # elevation direction (toward n) in tangent coordinates
    a = np.array([-e[1], e[0]])  # azimuth direction
    sigma_elev = sigma_m * s_e / float(np.linalg.norm(q))  # d(elevation)/d(height): r / |q|^2 with n = z
    info = np.outer(e, e) / sigma_elev**2 + np.outer(a, a) / GROUND_AZIMUTH_SIGMA_RAD**2
    g = cfg.ground
    noise = robust(gtsam.noiseModel.Gaussian.Information(info), g.robust,
                   threshold(g.robust_k, 1, cfg) * _outlier_share(sigma_m, outlier_sigma_m))
    return gtsam.BearingFactor3D(pose_key, landmark_key, measured, noise)


# The floor frame's yaw and horizontal position against its base: not measured by the floor, held tight.
FLOOR_FRAME_TIGHT_SIGMA = 1e-3


def floor_frame_factor(k: int, tilt_sigma_rad: float, height_sigma_m: float):
    """Keyframe k's floor frame ``F(k)`` against its base pose ``X(k)``: the same pose, but for a roll and pitch
    of ``tilt_sigma_rad`` and a height of ``height_sigma_m`` (Pose3 tangent order: rotation x y z, translation
    x y z); yaw and horizontal position held to ``FLOOR_FRAME_TIGHT_SIGMA``. The floor's information about the
    keyframe's height is bounded by this sigma however many floor points are tied to ``F(k)``."""
    sig = np.array([tilt_sigma_rad, tilt_sigma_rad, FLOOR_FRAME_TIGHT_SIGMA, FLOOR_FRAME_TIGHT_SIGMA,
                    FLOOR_FRAME_TIGHT_SIGMA, height_sigma_m])
    return gtsam.BetweenFactorPose3(X(k), F(k), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(sig))


def _floor_depth_error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
    """``Logmap(T_world_base^-1 T_world_floor)`` against a pure drop of ``d`` along the base's z axis."""
    kx, kf, kd = this.keys()
    H1 = np.zeros((6, 6), order="F")
    H2 = np.zeros((6, 6), order="F")
    Hl = np.zeros((6, 6), order="F")
    rel = values.atPose3(kx).between(values.atPose3(kf), H1, H2)
    xi = gtsam.Pose3.Logmap(rel, Hl)
    err = np.asarray(xi, float).copy()
    err[5] += values.atDouble(kd)
    if H is not None:
        H[0] = Hl @ H1
        H[1] = Hl @ H2
        H[2] = np.array([[0.0], [0.0], [0.0], [0.0], [0.0], [1.0]])
    return err


def floor_depth_factor(k: int, depth_key: int):
    """Keyframe k's floor frame ``F(k)`` is its base pose ``X(k)`` dropped by the floor depth ``d`` (state
    ``depth_key``, shared by the keyframes of a block) along the base's z axis, held to
    ``FLOOR_FRAME_TIGHT_SIGMA`` in all six directions: the floor points tied to ``F(k)`` measure the floor at
    ``camera_height_m + d`` below the camera, so the floor's information about the scale passes through ``d``,
    whose prior (``floor_depth_prior``) bounds it however many points the floor holds. A Python factor, one per
    keyframe with floor points (not one per point)."""
    noise = gtsam.noiseModel.Isotropic.Sigma(6, FLOOR_FRAME_TIGHT_SIGMA)
    return gtsam.CustomFactor(noise, [X(k), F(k), depth_key], _floor_depth_error)


def floor_depth_prior(k: int, depth_m: float, sigma_m: float):
    """What is known of the floor's depth below its configured height when its chain starts (or restarts)."""
    return gtsam.PriorFactorDouble(D(k), float(depth_m), gtsam.noiseModel.Isotropic.Sigma(1, sigma_m))


def floor_depth_walk(k_prev: int, k: int, sigma_m: float):
    """The floor's depth drifts slowly along the way (the road's crown, the load on the suspension)."""
    return gtsam.BetweenFactorDouble(D(k_prev), D(k), 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma_m))


def _outlier_share(sigma_m: float, outlier_sigma_m: float | None) -> float:
    """The robust threshold's factor that keeps it at ``outlier_sigma_m`` sigmas in metres for a factor of sigma
    ``sigma_m`` (1 when they are the same)."""
    return 1.0 if outlier_sigma_m is None else float(outlier_sigma_m) / float(sigma_m)


def _level_height_error(up: np.ndarray, floor_z: float, this: gtsam.CustomFactor, values: gtsam.Values,
                        H: list | None) -> np.ndarray:
    """Height of a floor point above the base origin along the floor's normal ``up``, less ``floor_z``."""
    kx, kl = this.keys()
    T = values.atPose3(kx)
    p = values.atPoint3(kl)
    R, t = T.rotation().matrix(), T.translation()
    err = np.array([float(up @ (p - t)) - floor_z])
    if H is not None:
        # GTSAM's Pose3 tangent is [w, v] with t' = t + R v: the residual does not depend on w.
        J_pose = np.zeros((1, 6))
        J_pose[0, 3:] = -(up @ R)
        H[0] = J_pose
        H[1] = up.reshape(1, 3).copy()
    return err


def level_ground_factor(pose_key: int, landmark_key: int, up_world: np.ndarray, floor_z: float, sigma_m: float,
                        cfg: BackendConfig, outlier_sigma_m: float | None = None):
    """Ties a floor landmark to the floor under a rocking base: its height above the base origin,
    measured along the floor's normal ``up_world`` (world frame, fixed when the factor is made), is
    ``floor_z``.

    Unlike :func:`ground_factor` it leaves the keyframe's attitude alone: when the chassis rocks on its
    suspension the base's xy plane is not the floor, and tying the point to it would turn the rocking
    into a height error that the smoother partly pays with scale (measured: a figure eight rocking by
    1 deg ended with its wheel scale 1% off). On a level base the native factor is kept, because there
    the floor points holding the base's attitude help. 1-D, sigma ``sigma_m``, robust like the native one.
    A Python factor (no native pose-to-point height factor in GTSAM's Python bindings), used only while
    the base rocks.
    """
    up = np.asarray(up_world, float)
    up = up / np.linalg.norm(up)
    g = cfg.ground
    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, sigma_m), g.robust,
                   threshold(g.robust_k, 1, cfg) * _outlier_share(sigma_m, outlier_sigma_m))
    return gtsam.CustomFactor(noise, [pose_key, landmark_key], partial(_level_height_error, up, float(floor_z)))
