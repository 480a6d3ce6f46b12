"""Dataset loaders on small fixtures written in their real layouts, and KITTI regression."""

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import SHARED_DATA, make_config

from windowvo import io
from windowvo.config import config_from_dict, load_config
from windowvo.errors import CalibrationError, SequenceError
from windowvo.eval.baselines import essential_chaining
from windowvo.eval.metrics import evaluate
from windowvo.geometry import make_T, rpy_to_R
from windowvo.io import euroc, kitti
from windowvo.io.sequence import load_native
from windowvo.runtime.job import run_and_report, run_job

R_BC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _images(folder: Path, n: int, size=(64, 48)) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    rng = np.random.default_rng(0)
    for i in range(n):
        name = f"{i:06d}.png"
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (size[1], size[0]), dtype=np.uint8))
        names.append(name)
    return names


def _cam_poses(n: int) -> list[np.ndarray]:
    """Camera-frame motion: forward along camera z with a slow turn about camera y."""
    return [make_T(rpy_to_R(0.0, 0.02 * i, 0.0), [0.01 * i, 0.0, 0.5 * i]) for i in range(n)]


def test_kitti_fixture(tmp_path):
    root = tmp_path / "kitti"
    _images(root / "image_0", 5)
    (root / "calib.txt").write_text(
        "P0: 700 0 30 0 0 705 20 0 0 0 1 0\nP1: 700 0 30 -378 0 705 20 0 0 0 1 0\n")
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(5)))
    poses = _cam_poses(5)
    (root / "poses.txt").write_text("".join(" ".join(f"{x:.9e}" for x in T[:3].ravel()) + "\n" for T in poses))
    seq = kitti.load_kitti(root)
    assert (seq.camera.fx, seq.camera.fy, seq.camera.cx, seq.camera.cy) == (700, 705, 30, 20)
    assert abs(kitti.read_kitti_calib(root / "calib.txt")[1] - 0.54) < 1e-9
    # the base lies on the road 1.65 m below camera 0
    assert np.allclose(seq.camera.T_base_cam[:3, 3], [0.0, 0.0, 1.65])
    # camera moving along its z axis is the base moving along x (forward)
    gt = seq.groundtruth.T_world_base
    assert np.allclose(gt[0], np.eye(4))
    assert np.allclose(gt[2][:3, 3], [1.0, -0.02, 0.0], atol=1e-9)
    assert np.allclose(gt[3][:3, :3], R_BC @ poses[3][:3, :3] @ R_BC.T)
    (root / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(SequenceError, match="expected 12 numbers"):
        kitti.load_kitti(root)
    (root / "calib.txt").write_text("P1: 1 2\n")
    with pytest.raises(CalibrationError):
        kitti.load_kitti(root)


def rodrigues(axis, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about ``axis`` (written out here, independent of windowvo.geometry)."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


# Ground-truth motion of the fixtures: a constant-rate rotation about a skewed axis, starting
# from a non-identity attitude, and a constant velocity, so that interpolation is exact and a
# quaternion read in the wrong order (w first vs w last) or with permuted axes gives other poses.
AXIS = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
ALPHA0, OMEGA = 0.7, 0.8  # rad, rad/s
VEL = np.array([0.3, -0.2, 0.5])  # m/s


def quat_xyzw(angle: float) -> list[float]:
    s = np.sin(angle / 2.0)
    return [AXIS[0] * s, AXIS[1] * s, AXIS[2] * s, np.cos(angle / 2.0)]


def expected_anchored(dt: float) -> np.ndarray:
    """T_first_k of a frame moving as above, dt after the first image: R(axis, omega dt) and
    R(axis, alpha0 + omega t_first)^T (vel dt)."""
    return make_T(rodrigues(AXIS, OMEGA * dt), rodrigues(AXIS, ALPHA0).T @ (VEL * dt))


def test_tum_fixture(tmp_path):
    root = tmp_path / "tum"
    names = _images(root / "rgb", 4)
    t_img = 100.0 + 0.05 * np.arange(4)
    (root / "rgb.txt").write_text("# color images\n# file\n# timestamp filename\n" +
                                  "".join(f"{t:.6f} rgb/{n}\n" for t, n in zip(t_img, names)))
    # ground truth at 100 Hz: pose of the camera (optical frame) in the mocap world, alpha(100 s) = ALPHA0
    tg = 99.9 + 0.01 * np.arange(40)
    rows = []
    for t in tg:
        q = quat_xyzw(ALPHA0 + OMEGA * (t - 100.0))
        p = np.array([1.0, 2.0, 1.5]) + VEL * (t - 100.0)
        rows.append(f"{t:.4f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}")
    (root / "groundtruth.txt").write_text("# ground truth\n# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    cfg = config_from_dict({"sequence": str(root), "output": str(tmp_path / "o"), "dataset": "tum",
                            "camera": {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}})
    seq = io.load(cfg)
    assert len(seq) == 4 and seq.camera.fx == 50
    gt = seq.groundtruth
    assert np.allclose(gt.timestamps, t_img)
    # base = camera with robot axes: T_world_base = T_base_cam T_first_k T_cam_base
    T_bc = make_T(R_BC, [0.0, 0.0, 0.0])
    for k in range(4):
        expected = T_bc @ expected_anchored(t_img[k] - 100.0) @ np.linalg.inv(T_bc)
        assert np.allclose(gt.T_world_base[k], expected, atol=1e-7), k
    # the camera's optical axis (z) maps to the base's forward axis (x)
    assert np.allclose(R_BC @ np.array([0.0, 0.0, 1.0]), [1.0, 0.0, 0.0])
    with pytest.raises(CalibrationError, match="camera"):
        io.load(config_from_dict({"sequence": str(root), "output": "o", "dataset": "tum"}))


def _euroc(tmp_path) -> Path:
    mav = tmp_path / "euroc" / "mav0"
    names = _images(mav / "cam0" / "data", 4, size=(752, 480))
    t_ns = 1403636579763555584 + 50_000_000 * np.arange(4)
    (mav / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n" +
                                           "".join(f"{t},{n}\n" for t, n in zip(t_ns, names)))
    (mav / "cam0" / "sensor.yaml").write_text("""%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
""")
    gt_dir = mav / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    # body B in world R at 200 Hz, alpha = ALPHA0 at the first image; columns p x y z, q w x y z, then
    # velocity and biases
    tg = t_ns[0] - 10_000_000 + 5_000_000 * np.arange(50)
    rows = []
    for t in tg:
        dt = (int(t) - int(t_ns[0])) * 1e-9
        x, y, z, w = quat_xyzw(ALPHA0 + OMEGA * dt)
        p = np.array([4.0, -1.0, 0.8]) + VEL * dt
        rows.append(f"{t},{p[0]:.12f},{p[1]:.12f},{p[2]:.12f},{w:.12f},{x:.12f},{y:.12f},{z:.12f}" + ",0" * 9)
    (gt_dir / "data.csv").write_text("#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],"
                                     "q_RS_z [],v_RS_R_x,v_RS_R_y,v_RS_R_z,b_w_x,b_w_y,b_w_z,b_a_x,b_a_y,b_a_z\n"
                                     + "\n".join(rows) + "\n")
    return tmp_path / "euroc"


def test_euroc_fixture(tmp_path):
    seq = euroc.load_euroc(_euroc(tmp_path))
    cam = seq.camera
    assert cam.distortion_model.value == "radtan" and len(cam.distortion) == 4
    assert abs(cam.fx - 458.654) < 1e-9 and abs(cam.T_base_cam[0, 3] + 0.0216401454975) < 1e-12
    gt = seq.groundtruth
    assert len(gt) == 4
    # base = body: ground truth is T_R_B re-anchored at the first image
    for k in range(4):
        assert np.allclose(gt.T_world_base[k], expected_anchored(0.05 * k), atol=1e-7), k


@pytest.mark.parametrize("kind", ["tum", "euroc"])
def test_planar_prior_is_off_by_default_for_handheld_and_drone_layouts(tmp_path, caplog, kind):
    """TUM (hand-held) and EuRoC (drone) have no level, z-up base: the roll/pitch prior is off by
    default, with a log line; an explicit setting in the config wins."""
    if kind == "tum":
        root = tmp_path / "tum"
        names = _images(root / "rgb", 3)
        (root / "rgb.txt").write_text("".join(f"{100 + 0.05 * i:.6f} rgb/{n}\n" for i, n in enumerate(names)))
        extra = {"camera": {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}}
    else:
        root = _euroc(tmp_path)
        extra = {}
    base = {"sequence": str(root), "output": str(tmp_path / "o"), "dataset": kind, **extra}
    # applied while the config is built, so the validated (and resolved) config says what runs
    with caplog.at_level(logging.INFO, logger="windowvo"):
        cfg = config_from_dict(dict(base))
    assert cfg.backend.planar_prior.enabled is False
    assert cfg.to_yaml_dict()["backend"]["planar_prior"]["enabled"] is False
    assert any("planar roll/pitch prior is off" in r.getMessage() for r in caplog.records)
    io.load(cfg)  # the loader changes nothing more
    assert cfg.backend.planar_prior.enabled is False
    # other planar-prior keys do not count as a choice about the prior itself
    cfg = config_from_dict({**base, "backend": {"planar_prior": {"sigma_rad": 0.2}}})
    assert cfg.backend.planar_prior.enabled is False and cfg.backend.planar_prior.sigma_rad == 0.2
    # explicit: the user's setting wins, from the file or from a dotted override
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="windowvo"):
        cfg = config_from_dict({**base, "backend": {"planar_prior": {"enabled": True}}})
    io.load(cfg)
    assert cfg.backend.planar_prior.enabled is True
    assert not any("planar roll/pitch prior" in r.getMessage() for r in caplog.records)
    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text(yaml.safe_dump(base))
    cfg = load_config(cfg_path, ["backend.planar_prior.enabled=true"])
    assert cfg.backend.planar_prior.enabled is True


def test_planar_prior_stays_on_for_ground_robot_layouts(tmp_path, short_loop):
    cfg = config_from_dict({"sequence": str(short_loop), "output": str(tmp_path / "o")})
    io.load(cfg)
    assert cfg.dataset.value == "native" and cfg.backend.planar_prior.enabled is True
    root = tmp_path / "kitti"
    _images(root / "image_0", 3)
    (root / "calib.txt").write_text("P0: 700 0 30 0 0 705 20 0 0 0 1 0\n")
    (root / "times.txt").write_text("0.0\n0.1\n0.2\n")
    cfg = config_from_dict({"sequence": str(root), "output": str(tmp_path / "o"), "dataset": "kitti"})
    io.load(cfg)
    assert cfg.backend.planar_prior.enabled is True


def test_folder_and_convert(tmp_path):
    root = tmp_path / "plain"
    _images(root, 6)
    cfg = config_from_dict({"sequence": str(root), "output": str(tmp_path / "o"), "dataset": "folder", "fps": 10,
                            "camera": {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}})
    seq = io.load(cfg)
    assert len(seq) == 6 and np.allclose(np.diff(seq.timestamps), 0.1)
    from windowvo.tools.convert import convert

    convert(seq, tmp_path / "native")
    back = load_native(tmp_path / "native")
    assert len(back) == 6 and back.camera.fx == 50


def test_odometry_synthesis_is_labelled(tmp_path, short_loop):
    cfg = config_from_dict({"sequence": str(short_loop), "output": str(tmp_path / "o"),
                            "odometry_synthesis": {"enabled": True}})
    seq = load_native(short_loop)
    seq.odometry = None
    seq = io.finish_sequence(seq, cfg)
    assert seq.odometry.synthetic
    assert any("SYNTHETIC" in w for w in seq.warnings)


# ---------------------------------------------------------------------------- KITTI regression

KITTI = ["kitti06_000-050", "kitti01_000-050"]


@pytest.mark.slow
@pytest.mark.parametrize("name", KITTI)
def test_kitti_with_synthetic_wheels(tmp_path, name):
    root = SHARED_DATA / name
    if not root.is_dir():
        pytest.skip(f"{root} not present")
    cfg = make_config(root, tmp_path / "out", dataset="kitti",
                      odometry_synthesis={"enabled": True, "scale_error": 0.01, "yaw_bias_per_m": 0.005})
    rep = run_job(cfg)
    ours = rep.accuracy.ate_se3_rmse_m
    wheel = rep.wheel_accuracy.ate_se3_rmse_m
    chain = essential_chaining(rep.sequence)
    chain_acc = evaluate(rep.sequence.groundtruth, chain.trajectory)
    print(f"{name}: windowvo ATE {ours:.3f} m, wheel-only {wheel:.3f} m, E-chaining {chain_acc.ate_se3_rmse_m:.3f} m")
    assert rep.sequence.odometry.synthetic
    assert ours <= 0.5 * wheel
    assert ours < chain_acc.ate_se3_rmse_m


@pytest.mark.parametrize("name", KITTI)
def test_kitti_monocular_is_metric(tmp_path, name):
    """No wheels: the road at camera 0's known height (1.65 m) makes the run metric (the metric-scale issue's
    bound: SE(3) ATE <= 2% of the distance). Measured when written: 0.78 m over 60 m (06), 0.34 m over 52 m
    (01); before, both stayed up to scale (their first keyframes see no road; 2.85 m and 1.93 m)."""
    root = SHARED_DATA / name
    if not root.is_dir():
        pytest.skip(f"{root} not present")
    r = run_and_report(make_config(root, tmp_path / "out", dataset="kitti"))
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    acc = summary["accuracy"]
    print(f"{name}: monocular ATE SE(3) {acc['ate_se3_rmse_m']:.3f} m, Sim(3) {acc['ate_sim3_rmse_m']:.3f} m over "
          f"{acc['path_length_m']:.1f} m, metric from frame {r.metric_from_frame}, the floor taken back after a "
          f"scale drift at {r.floor_scale_reanchors} keyframes")
    assert r.monocular and r.metric and r.scale_sources == ["ground plane (camera height)"]
    assert summary["metric"] and summary["floor_scale_reanchors"] == r.floor_scale_reanchors
    assert acc["ate_se3_rmse_m"] <= 0.02 * acc["path_length_m"]


@pytest.mark.slow
@pytest.mark.parametrize("name", KITTI)
def test_kitti_road_region_with_its_pitch_beats_the_wheels_alone(tmp_path, name):
    """The real road with wheels +2% and -3% (the scale suite's KITTI cases): its corners give the fused run no floor
    point, so the road's scale comes from ``ground.road_region``, which searches the floor's pitch (KITTI's camera is
    about 1 deg against its road). Fused ATE SE(3) at most 0.8x the wheels alone and within 2x of its own Sim(3)
    (the scale error mostly gone). When written: KITTI 06 0.033 / 0.153 m against 0.479 / 0.629 m, KITTI 01
    0.219 / 0.280 m against 0.428 / 0.392 m (0.07-0.71x; the 0.8x bound set after that first measurement), the
    pitch found +1.06 and +1.55 deg (stereo says 1.2-1.7 deg on KITTI 01's first half); with the set-up's pitch
    (``pitch_search_deg: 0``) KITTI 06 +2% was 1.395 m and KITTI 01 +2% 0.727 m, worse than the wheels alone."""
    root = SHARED_DATA / name
    if not root.is_dir():
        pytest.skip(f"{root} not present")
    for scale in (0.02, -0.03):
        cfg = make_config(root, tmp_path / f"out{scale}", dataset="kitti",
                          odometry_synthesis={"enabled": True, "scale_error": scale, "yaw_bias_per_m": 0.002},
                          backend={"ground": {"road_region": {"enabled": True}}})
        rep = run_job(cfg)
        ours, wheel = rep.accuracy, rep.wheel_accuracy.ate_se3_rmse_m
        pitch = [r.road_pitch_deg for r in rep.result.records if np.isfinite(r.road_pitch_deg)]
        print(f"{name} wheels {scale:+.0%}: fused ATE SE(3) {ours.ate_se3_rmse_m:.3f} m, Sim(3) "
              f"{ours.ate_sim3_rmse_m:.3f} m, wheels alone {wheel:.3f} m; region steps {len(pitch)}, pitch "
              f"{np.median(pitch):+.2f} deg (median)")
        assert ours.ate_se3_rmse_m <= 0.8 * wheel
        assert ours.ate_se3_rmse_m <= 2.0 * ours.ate_sim3_rmse_m
