"""The floor model on its own (``windowvo/backend/floor.py``, ``FloorModel``): the ground cue's switch for a
camera too low, the mount judgement that switches to the learnt floor normal (once), and the floor plane it
then ties floor points to. (Its floor after a monocular scale drift is tested in test_ground.py.)"""

import numpy as np
import pytest

from windowvo.backend.floor import MIN_CAMERA_HEIGHT_M, FloorModel
from windowvo.backend.landmarks import LandmarkManager
from windowvo.config import BackendConfig, MountCalibration
from windowvo.geometry import rpy_to_R
from windowvo.synth.generate import SynthSpec, camera_for
from windowvo.synth.paths import PathKind


@pytest.fixture(scope="module")
def camera():
    return camera_for(SynthSpec(path=PathKind.LOOP, duration_s=2.0, seed=1))


def _model(camera, use_odometry: bool = True, **ground) -> FloorModel:
    cfg = BackendConfig(ground=ground)
    return FloorModel(camera, cfg, use_odometry, LandmarkManager(camera, cfg), {})


def test_a_camera_too_low_switches_the_ground_cue_off(camera):
    low = _model(camera, use_odometry=False, camera_height_m=MIN_CAMERA_HEIGHT_M / 2)
    assert not low.use_ground and not low.waiting_for_floor() and not low.ground_active()
    born = [(1, np.array([2.0, 0.0, 0.0])), (2, np.array([3.0, 0.5, 0.0]))]
    mask, fit = low.floor_of(0, born, np.eye(4))
    assert fit is None and mask.tolist() == [False, False]
    mono = _model(camera, use_odometry=False)  # monocular with the cue: up to scale until the floor is seen
    assert mono.use_ground and mono.waiting_for_floor() and not mono.metric
    assert mono.floor_offset(None) == pytest.approx(0.0)  # base origin on the floor: its z is 0


@pytest.mark.parametrize("mode", [MountCalibration.AUTO, MountCalibration.OFF])
def test_the_mount_judgement_switches_once_to_the_learnt_normal(camera, mode):
    fm = _model(camera, mount_calibration=mode, mount_min_fits=10)
    tilted = rpy_to_R(0.0, np.radians(1.5), 0.0)[:, 2]  # a mount pitched by 1.5 deg
    assert fm.floor_normal_base() is None
    for i in range(12):
        fm.floor_attitude.add(tilted)
        switched = fm.judge_mount(i)
        assert switched == (mode is MountCalibration.AUTO and i == 9), i  # ready (and significant) at 10 fits
    n = fm.floor_normal_base()
    if mode is MountCalibration.OFF:
        assert n is None and not fm.retie_pending
        return
    assert fm.retie_pending and fm.mount_normal_used
    assert n is not None and np.degrees(np.arccos(np.clip(n @ tilted, -1, 1))) < 1e-6


def test_a_keyframes_floor_points_share_one_error_when_asked(camera):
    """sigma_common_fraction: n points of a keyframe tell its floor's height to sqrt(own^2 / n + common^2), never
    better than the common part; the robust threshold stays at the point's own sigma (a kerb is still an outlier)."""
    import gtsam

    from windowvo.backend import factors as fac

    indep = _model(camera)
    shared = _model(camera, sigma_common_fraction=0.015)
    h = shared.camera_height_m
    own, common = 0.03 * h, 0.015 * h
    assert indep.point_sigma_m(100) == pytest.approx(own)  # the default: independent points
    for n in (1, 4, 100):
        s = shared.point_sigma_m(n)
        # n factors of sigma s inform the common height like one of sigma s / sqrt(n)
        assert s / np.sqrt(n) == pytest.approx(np.sqrt(own**2 / n + common**2))
        assert s / np.sqrt(n) >= common
    # The factor's robust threshold stays at 1.96 of the point's own sigma, whatever the widened sigma: a point
    # 1.5 own sigmas off the floor costs the quadratic (Gaussian) error, one 2.5 own sigmas off less (Huber).
    p_base = np.array([2.0, 0.3, 0.0])
    s_wide = shared.point_sigma_m(50)
    f_wide = fac.ground_factor(1, 2, p_base, 0.0, s_wide, shared.cfg, None, own)
    for off, robust in ((1.5, False), (2.5, True)):
        vals = gtsam.Values()
        vals.insert(1, gtsam.Pose3())
        vals.insert(2, gtsam.Point3(2.0, 0.3, off * own))
        gaussian = 0.5 * (off * own / s_wide) ** 2  # the whitened height error, squared, halved
        assert (f_wide.error(vals) < 0.98 * gaussian) is robust, (off, f_wide.error(vals), gaussian)


def test_a_far_floor_point_carries_the_floors_tilt_in_its_sigma(camera):
    """ground.sigma_tilt_deg: a point's height sigma grows with its range by the floor's attitude error against the
    base (hypot of its own sigma and r tan(tilt)); 0 leaves it as it was, and the robust threshold widens with it."""
    fixed = _model(camera, sigma_tilt_deg=1.0)
    own = fixed.ground_sigma_m
    near, far = np.array([0.5, 0.0, 0.0]), np.array([8.0, 6.0, -0.4])  # 0.5 m and 10 m ahead
    s_near, o_near = fixed.range_sigmas_m(own, near)
    s_far, o_far = fixed.range_sigmas_m(own, far)
    t = np.tan(np.radians(1.0))
    assert s_near == pytest.approx(np.hypot(own, 0.5 * t))
    assert s_far == pytest.approx(np.hypot(own, 10.0 * t)) and s_far > 5 * own
    assert o_far == pytest.approx(s_far) and o_near == pytest.approx(s_near)
    exact = _model(camera, sigma_tilt_deg=0.0)
    assert exact.range_sigmas_m(own, far) == (own, own)



def test_the_log_says_first_test_then_again_after_a_disagreement(camera, caplog):
    """The cue check's log: a first passing test is not "agree again"; agreement after a disagreement is."""
    import logging

    fm = _model(camera)
    fm.metric = True
    caplog.set_level(logging.INFO, logger="windowvo")
    h = fm.camera_height_m
    for k in range(1, 13):  # the wheels and the floor agree
        fm.fit_height_m = h
        fm.check_cues(k, 0.2, 0.2)
    assert any("agree at their first test" in r.message for r in caplog.records)
    assert not any("agree again" in r.message for r in caplog.records)
    caplog.clear()
    for k in range(13, 25):  # the floor says 15% more scale, then agrees again
        fm.fit_height_m = h / 1.15 if k < 19 else h
        fm.check_cues(k, 0.2, 0.2)
    messages = [r.message for r in caplog.records]
    assert any("disagree" in m for m in messages) and any("agree again" in m for m in messages), messages
