"""The wheels' time offset from the speed changes: the image's frame-to-frame motion against the wheels' distance.

A robot that stops and starts on a straight line shows no offset in its turns; its stops show it (a wheel reading
taken ``dt`` late is short by ``acceleration * dt * frame interval`` on every frame of a ramp)."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from windowvo.backend.wheel_clock import WheelClock, estimate_offset
from windowvo.io.odometry_synthesis import integrate_wheel_odometry

FPS = 20.0


def _speed(t: np.ndarray, stops: bool = True) -> np.ndarray:
    """The renderer's stop-and-go: 5 s driving at 0.8 m/s, 3 s standing, 0.5 s ramps; or 0.8 m/s throughout."""
    if not stops:
        return np.full_like(t, 0.8)
    cyc = np.mod(t, 8.0)
    return 0.8 * np.minimum(np.clip(cyc / 0.5, 0, 1), np.clip((5.0 - cyc) / 0.5, 0, 1)) * (cyc < 5.0)


def _stop_and_go(offset_s: float, seed: int = 0, stops: bool = True, duration_s: float = 16.0,
                 flow_noise_px: float = 0.04):
    """Wheels at 100 Hz on their own clock (``t_wheels = t_camera + offset_s``), 2% long, with the renderer's
    distance noise (0.002 m/sqrt(m)); a straight line (no turn shows the offset). Frames at FPS: the image moves by a gain (the scene's depth: it
    drifts by +-20%) times the true distance between two frames, plus noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 0.01)
    s_true = np.concatenate([[0.0], np.cumsum(0.5 * (_speed(t[1:], stops) + _speed(t[:-1], stops)) * 0.01)])
    wheels = integrate_wheel_odometry(t + offset_s, np.concatenate([[0.0], np.diff(s_true)]), np.zeros_like(t),
                                      scale_error=0.02, yaw_bias_per_m=0.0, distance_noise=0.002, yaw_noise=0.002,
                                      rng=rng)
    clock = WheelClock()
    frames = np.arange(0.0, duration_s - 0.2, 1.0 / FPS)
    for t0, t1 in itertools.pairwise(frames):
        gain = 60.0 * (1.0 + 0.2 * np.sin(0.3 * t1))
        step = float(np.interp(t1, t, s_true) - np.interp(t0, t, s_true))
        clock.add_flow(t0, t1, gain * step + rng.normal(0.0, flow_noise_px))
    return clock, wheels


@pytest.mark.parametrize("offset_ms", [15.0, 30.0, 50.0, -20.0])
def test_stops_show_the_offset(offset_ms):
    clock, wheels = _stop_and_go(offset_ms / 1000.0, duration_s=30.0)
    est = clock.update(wheels)
    assert est.observable and est.from_speed and est.zero_rejected, est
    # The estimate moves with the shift: within its 99% interval here; the 3 ms bar is the scatter's (next test).
    assert abs(est.offset_s * 1000.0 - offset_ms) < 2.58 * 1000.0 * est.sigma_s < 7.0, est


def test_the_estimates_scatter_as_their_sigma_says():
    """Over 20 seeds of the wheels' and the image's noise (30 s drives, three stops, 30 ms): every estimate is
    observable and told from zero, 80% within the issue's 3 ms, and their scatter is what their sigma claims (the
    widening FLOW_SIGMA_WIDENING: without it they scatter twice as far as their sigma)."""
    err, sig = [], []
    for seed in range(20):
        clock, wheels = _stop_and_go(0.03, seed=seed, duration_s=30.0)
        est = clock.update(wheels)
        assert est.observable and est.zero_rejected, (seed, est)
        err.append(est.offset_s - 0.03)
        sig.append(est.sigma_s)
    err_ms = 1000.0 * np.abs(err)
    assert np.mean(err_ms < 3.0) >= 0.8, err_ms
    assert np.all(np.abs(err) < 2.58 * np.array(sig)), (err_ms, sig)
    assert 0.5 < np.std(err) / np.median(sig) < 1.5, (np.std(err), np.median(sig))


@pytest.mark.parametrize("seed", range(10))
def test_a_zero_offset_is_not_taken_for_one(seed):
    """At a true zero the likelihood-ratio test does not reject zero (at 99%, on these seeds): nothing is applied."""
    clock, wheels = _stop_and_go(0.0, seed=seed)
    est = clock.update(wheels)
    assert not est.zero_rejected, est


def test_a_constant_speed_does_not_show_the_offset():
    """Without a speed change (and without turns) every offset fits: the speed part does not count."""
    clock, wheels = _stop_and_go(0.03, stops=False)
    est = clock.update(wheels)
    assert not est.observable and not est.from_speed, est


def _turning_stop_and_go(offset_s: float, flow_late_s: float = 0.0, seed: int = 0, duration_s: float = 30.0):
    """A path that turns (its heading a function of the distance) driven stop-and-go: both parts see the offset.
    ``flow_late_s`` makes the image's motion that much later than the truth (a part gone wrong)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 0.01)
    s_true = np.concatenate([[0.0], np.cumsum(0.5 * (_speed(t[1:]) + _speed(t[:-1])) * 0.01)])

    def yaw_true(tt):
        d = np.interp(tt, t, s_true)
        return 0.9 * np.sin(0.6 * d) + 0.3 * np.sin(1.7 * d)

    wheels = integrate_wheel_odometry(t + offset_s, np.concatenate([[0.0], np.diff(s_true)]),
                                      np.concatenate([[0.0], np.diff(yaw_true(t))]), scale_error=0.02,
                                      yaw_bias_per_m=0.005, distance_noise=0.002, yaw_noise=0.002, rng=rng)
    clock = WheelClock()
    moving = [tt for tt in np.arange(1.0, duration_s - 1.0, 0.15) if _speed(np.array([tt]))[0] > 0.1]
    for t0, t1 in itertools.pairwise(moving):
        if t1 - t0 < 0.2:  # no keyframe while standing: the interval over a stop is left out, as vision has none
            clock.add(t0, t1, float(yaw_true(t1) - yaw_true(t0) + rng.normal(0, 5e-4)))
    for t0, t1 in itertools.pairwise(np.arange(0.0, duration_s - 0.2, 1.0 / FPS)):
        step = float(np.interp(t1 - flow_late_s, t, s_true) - np.interp(t0 - flow_late_s, t, s_true))
        clock.add_flow(t0, t1, 60.0 * step + rng.normal(0.0, 0.04))
    return clock, wheels


def test_turns_and_speed_together():
    """Both parts counted at once (one chi-square curve): the estimate is on the offset, and the speed counted."""
    clock, wheels = _turning_stop_and_go(0.03)
    est = clock.update(wheels)
    assert est.observable and est.from_speed and abs(est.offset_s - 0.03) < 0.003, est


def test_turns_and_speed_that_disagree_give_no_estimate():
    """The image's motion 60 ms late against the turns: the two parts tell different offsets (a chi-square test of
    their difference) and are not added; no estimate, none applied."""
    clock, wheels = _turning_stop_and_go(0.03, flow_late_s=0.06)
    est = estimate_offset(list(clock.intervals), wheels, flows=list(clock.flows))
    assert not est.observable, est


def test_the_front_end_measures_the_image_motion():
    """``FrontendOutput.flow_px``: the median motion of the tracks between two frames, in pixels (a textured image
    moved by (3, 4) px: 5 px); nan on the first frame."""
    from windowvo.camera import CameraModel
    from windowvo.config import FrontendConfig, GateConfig, KeyframeConfig
    from windowvo.frontend.frontend import Frontend
    from windowvo.types import Frame

    rng = np.random.default_rng(1)
    big = cv2.GaussianBlur((rng.random((300, 380)) * 255).astype(np.uint8), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX)
    cam = CameraModel(width=320, height=240, fx=200.0, fy=200.0, cx=160.0, cy=120.0)
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(), GateConfig())
    first = fe.process(Frame(0, 0.0, np.ascontiguousarray(big[20:260, 20:340])))
    moved = fe.process(Frame(1, 0.05, np.ascontiguousarray(big[16:256, 17:337])))
    assert np.isnan(first.flow_px)
    assert abs(moved.flow_px - 5.0) < 0.2, moved.flow_px


# The scale suite's stop-and-go room (a loop at a constant turn rate per metre: its turns do not show the offset);
# its wheel clock is put 30 ms late (the stamps of odometry.csv alone).
STOPGO = "room_stopgo_-2pct_track5pct"
STOPGO_LATE_S = 0.03


@pytest.mark.slow
def test_a_late_clock_on_a_stop_and_go_drive(tmp_path_factory):
    """End to end: 30 ms added to the wheels' stamps of the stop-and-go room is estimated within 3 ms from its stops
    and applied part way in a first pass, and the run is made again with it from its first frame (a second pass,
    ``time_offset_second_pass``; the first pass's files and summary in ``first_pass/``). The second pass comes
    within 1.15x of the unshifted sequence's run and is better than the first pass and than the same late sequence
    read at the camera's times. Measured (scripts/wheel_clock_sweep.py): +0.9 ms error (sigma 2.9), applied from
    9.2 s in the first pass; ATE 0.0021 m (second pass), 0.0030 m (first pass), 0.0071 m (read at the camera's
    times), 0.0020 m (unshifted). Before the speed part the offset was not observable on this drive at any shift."""
    import json

    from test_wheel_clock import _run

    from windowvo.runtime.outfolder import FIRST_PASS_DIR
    from windowvo.synth.generate import shift_wheel_clock
    from windowvo.tools.scale_suite import ensure_rendered, rendered_cases

    root = tmp_path_factory.mktemp("stopgo")
    seq = ensure_rendered(next(c for c in rendered_cases() if c.name == STOPGO), root)
    late = shift_wheel_clock(seq, root / "late", STOPGO_LATE_S)
    clock, ate_second = _run(late, root / "estimate", "estimate")
    first = json.loads((root / "estimate" / FIRST_PASS_DIR / "summary.json").read_text())
    c1 = first["wheel_time_offset"]
    assert c1["observable"] and c1["from_speed_changes"], c1
    assert abs(c1["offset_ms"] - 1000.0 * STOPGO_LATE_S) < 3.0, c1
    assert c1["applied"] and c1["applied_since_s"] > 1.0, c1  # part way: what the second pass is for
    second = json.loads((root / "estimate" / "summary.json").read_text())["wheel_clock_first_pass"]
    assert second is not None and second["offset_ms"] == pytest.approx(c1["offset_ms"], abs=0.01), second
    assert clock["applied"] and clock["applied_since_s"] == 0.0, clock
    assert abs(clock["applied_ms"] - 1000.0 * STOPGO_LATE_S) < 3.0, clock
    ate_first = first["accuracy"]["ate_se3_rmse_m"]
    _, ate_off = _run(late, root / "off", "off")
    _, ate_plain = _run(seq, root / "plain", "estimate")
    assert not (root / "plain" / FIRST_PASS_DIR).exists()  # nothing applied on the unshifted drive: one pass
    assert ate_second < ate_first < ate_off, (ate_second, ate_first, ate_off)
    assert ate_second <= 1.15 * ate_plain, (ate_second, ate_plain)


def test_a_circle_driven_stop_and_go_does_not_show_the_offset_in_its_turns():
    """On a circle the heading changes in proportion to the distance: a stop-and-go drive changes the turn rate with
    the speed alone, which the wheels' own distance term fits at any offset. The turns do not count there (before
    they did, and put a 40 s warehouse loop's offset 30 ms off with a sigma of 3.6 ms); the speed part does."""
    from windowvo.backend.wheel_clock import _distance, _heading_rss

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 30.0, 0.01)
    s_true = np.concatenate([[0.0], np.cumsum(0.5 * (_speed(t[1:]) + _speed(t[:-1])) * 0.01)])
    wheels = integrate_wheel_odometry(t + 0.03, np.concatenate([[0.0], np.diff(s_true)]),
                                      np.concatenate([[0.0], np.diff(0.5 * s_true)]), scale_error=0.02,
                                      yaw_bias_per_m=0.005, distance_noise=0.002, yaw_noise=0.002, rng=rng)
    clock = WheelClock()
    # Keyframes every 0.15 s while moving; each interval from the newest keyframe at least 1 s earlier (the
    # stream's CLOCK_SPAN_S: across a stop too), as vision chains its heading.
    kfs = [tt for tt in np.arange(1.0, 29.0, 0.15) if _speed(np.array([tt]))[0] > 0.1]
    for i, t1 in enumerate(kfs):
        earlier = [t0 for t0 in kfs[:i] if t1 - t0 >= 1.0]
        if earlier:
            d = float(np.interp(t1, t, s_true) - np.interp(earlier[-1], t, s_true))
            clock.add(earlier[-1], t1, 0.5 * d + rng.normal(0, 5e-4))
    offsets = np.arange(-0.1, 0.1005, 0.001)
    rss, *_ = _heading_rss(list(clock.intervals), wheels, offsets, 0.1, _distance(wheels))
    assert rss is None
    assert not estimate_offset(list(clock.intervals), wheels).observable


@pytest.mark.slow
def test_a_second_pass_killed_is_resumed_as_the_second_pass(tmp_path):
    """SIGKILL during the second pass (the stop-and-go room, wheels 30 ms late) leaves the first pass whole in
    ``first_pass/``; ``--resume`` continues the second pass (wheels read at the first pass's exact estimate from the
    first frame) and ends with the uninterrupted run's trajectory, its replay the killed run's to the last bit."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from test_faults import ENV, TIMEOUT, _journal_frames, cli

    from windowvo.runtime.outfolder import FIRST_PASS_DIR
    from windowvo.synth.generate import shift_wheel_clock
    from windowvo.tools.scale_suite import ensure_rendered, rendered_cases

    seq = ensure_rendered(next(c for c in rendered_cases() if c.name == STOPGO), tmp_path)
    late = shift_wheel_clock(seq, tmp_path / "late", STOPGO_LATE_S)

    def config(out):
        path = tmp_path / f"{out.name}.yaml"
        path.write_text(f"sequence: {late}\noutput: {out}\nviz:\n  rerun: 'off'\nrun_mode: sequential\n")
        return str(path)

    ref = tmp_path / "ref"
    assert cli(config(ref)).returncode == 0
    assert (ref / FIRST_PASS_DIR / "summary.json").is_file()  # the uninterrupted run took a second pass
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", config(out), "--no-progress", "-q"], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < TIMEOUT and not (
            (out / FIRST_PASS_DIR / "summary.json").is_file() and _journal_frames(out) >= 120):
        time.sleep(0.002)
    assert proc.poll() is None, "the run ended before its second pass could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=TIMEOUT)
    assert not (out / "summary.json").exists() and (out / FIRST_PASS_DIR / "trajectory.txt").is_file()
    r = cli(config(out), "--resume")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed"] is True and summary["replay_max_difference_m"] == 0.0, summary
    assert summary["wheel_time_offset"]["applied_since_s"] == 0.0, summary["wheel_time_offset"]
    traj, want = (np.loadtxt(d / "trajectory.txt", comments="#") for d in (out, ref))
    # to the file's last digit (1 um; the continuation is placed through the journal's pose of its seam frame)
    np.testing.assert_allclose(traj[:, 1:4], want[:, 1:4], rtol=0, atol=2e-6)
