"""The wheels' time offset to the camera, estimated from vision's and the wheels' heading changes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from windowvo.backend.wheel_clock import WheelClock, estimate_offset
from windowvo.config import WheelClockMode, robot_config_from_dict
from windowvo.errors import ConfigError
from windowvo.geometry import inv_T, planar_T
from windowvo.io.odometry import WheelOdometry
from windowvo.runtime.stream import CLOCK_UPDATE_EVERY, Odometry


def _drive(offset_s: float, turning: bool = True, seed: int = 0, yaw_scale: float = 0.03,
           yaw_bias_per_m: float = 0.01, duration_s: float = 30.0):
    """Wheels at 100 Hz on their own clock (``t_wheels = t_camera + offset_s``), with a track-width error, a yaw
    bias and noise; keyframes every 0.15 s with vision's heading change (0.5 mrad noise)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 0.01)

    def yaw_true(tt):
        return 0.9 * np.sin(0.45 * tt) + 0.3 * np.sin(1.3 * tt) if turning else 0.0 * tt

    speed = 0.8
    yaw_w = (1 + yaw_scale) * yaw_true(t) + yaw_bias_per_m * speed * t + np.cumsum(rng.normal(0, 2e-4, len(t)))
    x = np.cumsum(speed * 0.01 * np.cos(yaw_true(t)))
    y = np.cumsum(speed * 0.01 * np.sin(yaw_true(t)))
    wheels = WheelOdometry(t + offset_s, x, y, yaw_w)
    clock = WheelClock()
    kf = np.arange(1.0, duration_s - 1.0, 0.15)
    for t0, t1 in itertools.pairwise(kf):
        clock.add(t0, t1, float(yaw_true(t1) - yaw_true(t0) + rng.normal(0, 5e-4)))
    return clock, wheels


@pytest.mark.parametrize("offset_ms", [15.0, 30.0, 50.0, -20.0, 0.0])
def test_the_offset_is_found_within_3_ms(offset_ms):
    clock, wheels = _drive(offset_ms / 1000.0)
    est = clock.update(wheels)
    assert est.observable
    assert abs(est.offset_s * 1000.0 - offset_ms) < 3.0, est
    assert est.sigma_s < 0.003


def test_a_straight_drive_does_not_show_the_offset():
    clock, wheels = _drive(0.03, turning=False)
    est = clock.update(wheels)
    assert not est.observable and est.offset_s == 0.0


def test_too_few_intervals_give_no_estimate():
    clock, wheels = _drive(0.03)
    intervals = list(clock.intervals)[:5]
    assert not estimate_offset(intervals, wheels).observable


def test_an_unobservable_update_keeps_the_last_estimate():
    clock, wheels = _drive(0.025)
    first = clock.update(wheels)
    clock.intervals.clear()
    kept = clock.update(wheels)
    assert kept.offset_s == first.offset_s and kept.observable


def test_wheels_on_the_camera_clock_are_read_at_t_plus_the_offset():
    _, wheels = _drive(0.03)
    cam = wheels.on_camera_clock(0.03)
    t = 7.123
    i = int(np.searchsorted(wheels.timestamps, t + 0.03)) - 1  # the raw samples around t + offset, by hand
    s = (t + 0.03 - wheels.timestamps[i]) / (wheels.timestamps[i + 1] - wheels.timestamps[i])
    yaw = wheels.yaw[i] + s * (wheels.yaw[i + 1] - wheels.yaw[i])
    x = wheels.x[i] + s * (wheels.x[i + 1] - wheels.x[i])
    assert np.allclose(cam.pose_at(t), planar_T(float(x), wheels.y[i] + s * (wheels.y[i + 1] - wheels.y[i]),
                                                float(yaw)), atol=1e-9)
    assert wheels.on_camera_clock(0.0) is wheels


def _stream(mode: str, offset_s: float = 0.03, fixed_ms: float | None = None):
    """A streaming Odometry fed the wheels of ``_drive(offset_s)`` (its clock filled with the drive's intervals)."""
    from windowvo.synth.generate import SynthSpec, camera_for

    odo_cfg: dict = {"time_offset": mode} if fixed_ms is None else {"time_offset": mode, "time_offset_ms": fixed_ms}
    vo = Odometry(camera_for(SynthSpec(width=160, height=120, fx=90.0)), robot_config_from_dict(
        {"backend": {"odometry": odo_cfg}}))
    clock, wheels = _drive(offset_s)
    for t, x, y, yaw in zip(wheels.timestamps, wheels.x, wheels.y, wheels.yaw):
        vo.add_wheel_odometry(float(t), float(x), float(y), float(yaw))
    assert vo.clock is not None
    for iv in clock.intervals:
        vo.clock.add(iv.t0, iv.t1, iv.vision_yaw_rad)
    return vo, wheels


def _raw_delta(wheels: WheelOdometry, t0: float, t1: float) -> np.ndarray:
    def pose(t):
        return planar_T(*(float(np.interp(t, wheels.timestamps, a)) for a in (wheels.x, wheels.y, wheels.yaw)))
    return inv_T(pose(t0)) @ pose(t1)


def test_the_estimated_offset_is_applied_to_the_wheel_factors():
    vo, wheels = _stream("estimate", 0.03)
    vo.last_kf_time = 10.0
    vo._update_offset(20.0)
    assert abs(vo.wheel_offset_s - 0.03) < 0.003 and vo.offset_applied_since == 20.0
    step = vo._odom_step(10.0, 10.4)
    assert step is not None and step.ok
    assert np.allclose(step.T_prev_cur, _raw_delta(wheels, 10.0 + vo.wheel_offset_s, 10.4 + vo.wheel_offset_s),
                       atol=1e-9)
    assert not np.allclose(step.T_prev_cur, _raw_delta(wheels, 10.0, 10.4), atol=1e-4)  # the offset matters here
    # The standstill check reads the same shifted wheels.
    dist, turn = vo._odom_since_kf(10.4)
    d = _raw_delta(wheels, 10.0 + vo.wheel_offset_s, 10.4 + vo.wheel_offset_s)
    assert dist == pytest.approx(np.hypot(d[0, 3], d[1, 3])) and turn == pytest.approx(abs(np.arctan2(d[1, 0], d[0, 0])))
    rep = vo.wheel_time_offset()
    assert rep is not None and rep.applied_s == vo.wheel_offset_s and rep.applied_since_t == 20.0


@pytest.mark.parametrize("seed", range(6))
def test_a_zero_offset_is_told_from_a_real_one(seed):
    """The likelihood-ratio test against a zero offset: a 30 ms offset rejects zero, a true zero does not (at 99%,
    on these seeds), so a drive whose clocks agree is left as it is."""
    clock, wheels = _drive(0.03, seed=seed)
    assert estimate_offset(list(clock.intervals), wheels).zero_rejected is True  # a bool: it goes to summary.json
    clock, wheels = _drive(0.0, seed=seed)
    est = estimate_offset(list(clock.intervals), wheels)
    assert est.observable and not est.zero_rejected, est


def test_an_estimate_not_told_from_zero_is_not_applied():
    vo, _ = _stream("estimate", 0.0)
    vo._update_offset(20.0)
    assert vo.wheel_offset_s == 0.0 and vo.offset_applied_since is None
    rep = vo.wheel_time_offset()
    assert rep is not None and rep.observable and not rep.zero_rejected and rep.applied_s is None


def test_the_offset_is_re_estimated_only_every_few_new_intervals():
    vo, _ = _stream("estimate", 0.03)
    vo._update_offset(20.0)
    first = vo.wheel_offset_s
    for k in range(CLOCK_UPDATE_EVERY - 1):  # intervals that would move the estimate: not yet used
        vo.clock.add(20.0 + 0.1 * k, 20.1 + 0.1 * k, 5.0)
    vo._update_offset(21.0)
    assert vo.wheel_offset_s == first


def test_off_estimates_but_reads_the_wheels_at_the_camera_times():
    vo, wheels = _stream("off", 0.03)
    vo._update_offset(20.0)
    assert vo.wheel_offset_s == 0.0 and vo.offset_applied_since is None
    assert np.allclose(vo._odom_step(10.0, 10.4).T_prev_cur, _raw_delta(wheels, 10.0, 10.4), atol=1e-9)
    rep = vo.wheel_time_offset()
    assert rep is not None and rep.observable and abs(rep.offset_s - 0.03) < 0.003 and rep.applied_s is None


def test_a_fixed_offset_is_applied_from_the_start():
    vo, wheels = _stream("fixed", 0.03, fixed_ms=-12.5)
    vo._update_offset(20.0)  # the estimate does not replace a given offset
    assert vo.wheel_offset_s == -0.0125
    assert np.allclose(vo._odom_step(10.0, 10.4).T_prev_cur, _raw_delta(wheels, 9.9875, 10.3875), atol=1e-9)


def test_the_time_offset_keys_are_checked():
    assert robot_config_from_dict({"backend": {"odometry": {"time_offset": False}}}).backend.odometry.time_offset \
        is WheelClockMode.OFF  # YAML 1.1 reads a bare `off` as false
    with pytest.raises(ConfigError, match="time_offset_ms is set but time_offset is 'estimate'"):
        robot_config_from_dict({"backend": {"odometry": {"time_offset_ms": 15.0}}})
    with pytest.raises(ConfigError):
        robot_config_from_dict({"backend": {"odometry": {"time_offset": "fixed", "time_offset_ms": 5000.0}}})


# The scale suite's warehouse figure eight; its wheel clock is put 15 ms late (the stamps of odometry.csv alone).
CASE = "warehouse_fig8_yaw10mrad_+1pct"
# Where a late clock costs the run more than its noise (region off): the room's figure eight (0.0047-0.0051 m late
# against 0.0041-0.0042 m plain over floor seeds 0-4; the warehouse's figure eight: 0.018-0.025 m late against
# 0.020-0.025 m plain)
COST_CASE = "room_fig8_+2pct_track3pct"
LATE_S = 0.015


def _late(tmp_path_factory, name: str):
    """One render of the suite's case ``name``, and the same sequence with the wheels' clock LATE_S ahead."""
    from windowvo.synth.generate import shift_wheel_clock
    from windowvo.tools.scale_suite import ensure_rendered, rendered_cases

    root = tmp_path_factory.mktemp("clock")
    seq = ensure_rendered(next(c for c in rendered_cases() if c.name == name), root)
    return seq, shift_wheel_clock(seq, root / "late", LATE_S)


@pytest.fixture(scope="module")
def late_wheels(tmp_path_factory):
    return _late(tmp_path_factory, CASE)


def _run(seq, out, mode: str, road_region: bool = True) -> tuple[dict, float]:
    import json

    from conftest import make_config

    from windowvo.runtime.job import run_and_report

    run_and_report(make_config(seq, out, run_mode="sequential", backend={
        "odometry": {"time_offset": mode}, "ground": {"road_region": {"enabled": road_region}}}))
    summary = json.loads((out / "summary.json").read_text())
    return summary["wheel_time_offset"], summary["accuracy"]["ate_se3_rmse_m"]


@pytest.mark.slow
def test_a_late_wheel_clock_is_estimated_and_applied(late_wheels, tmp_path_factory, tmp_path):
    """End to end: 15 ms added to the wheels' stamps is estimated within 3 ms and applied (summary says so), with the
    defaults (the warehouse's figure eight: 15.1 ms); and where the wheels carry the scale between the floor's points
    (the floor's region off) and the late clock costs the run more than its noise (COST_CASE), the run with it
    applied is better than the same late sequence read at the camera's times (time_offset off): 0.0041 m applied,
    0.0047 m off, 0.0042 m plain (floor seeds 0-4: applied over off 0.81-0.88x). This comparison was first made on
    the warehouse's figure eight (0.0137 m applied, 0.0198 m off on the renders of OpenBLAS's AVX-512 kernels); on
    today's renders the late clock does not cost that run more than its floor seed does (0.018-0.025 m off against
    0.020-0.025 m plain, seeds 0-4) and applying it came out 0.98-1.33x of off: a comparison of noise. The issue's
    bar (within 1.05x of the plain run) is measured over a sweep (scripts/wheel_clock_sweep.py, docs/scale_suite.md),
    not by one case."""
    _, late = late_wheels
    clock, _ = _run(late, tmp_path / "late", "estimate")
    assert clock["observable"] and abs(clock["offset_ms"] - 1000.0 * LATE_S) < 3.0, clock
    assert clock["applied"] and abs(clock["applied_ms"] - 1000.0 * LATE_S) < 3.0, clock
    _, late_room = _late(tmp_path_factory, COST_CASE)
    _, ate_off = _run(late_room, tmp_path / "off", "off", road_region=False)
    _, ate_applied = _run(late_room, tmp_path / "late_wheels_only", "estimate", road_region=False)
    assert ate_applied < ate_off, (ate_applied, ate_off)


def test_the_summary_takes_numpy_values(tmp_path):
    """A value computed with NumPy (a numpy bool from a comparison, a float64, an array) must never cost a run its
    summary.json (the clock's test once gave a numpy bool: the run ended in a TypeError)."""
    import json

    from windowvo.runtime.outputs import write_summary

    write_summary({"flag": np.bool_(True), "x": np.float64(1.5), "v": np.arange(3)}, tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text()) == {"flag": True, "x": 1.5, "v": [0, 1, 2]}


def test_a_shifted_wheel_clock_moves_only_the_wheel_stamps(tmp_path):
    from windowvo.io.odometry import read_odometry_csv
    from windowvo.synth.generate import SynthSpec, generate_sequence, shift_wheel_clock

    seq = tmp_path / "seq"
    generate_sequence(seq, SynthSpec(duration_s=0.5, width=64, height=48, fx=40.0, write_images=False))
    late = shift_wheel_clock(seq, tmp_path / "late", 0.025)
    a, b = read_odometry_csv(seq / "odometry.csv"), read_odometry_csv(late / "odometry.csv")
    assert np.allclose(b.timestamps, a.timestamps + 0.025, atol=1e-6)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.yaw, b.yaw) and a.comment == b.comment
    assert (late / "times.txt").read_text() == (seq / "times.txt").read_text()
