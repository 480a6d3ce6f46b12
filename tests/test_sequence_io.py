"""Bad sequence input: one clear error line and exit code 2, never a traceback."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from windowvo.errors import CalibrationError, SequenceError
from windowvo.geometry import make_T, rpy_to_R
from windowvo.io.odometry import read_odometry_csv
from windowvo.io.sequence import load_native
from windowvo.io.trajectory import read_tum, write_tum


@pytest.fixture
def seq(short_loop, tmp_path) -> Path:
    dst = tmp_path / "seq"
    shutil.copytree(short_loop, dst)
    return dst


def run_cli(seq: Path, out: Path):
    cfg = out.parent / "c.yaml"
    cfg.write_text(f"sequence: {seq}\noutput: {out}\nviz:\n  rerun: 'off'\nprogress: false\nmax_frames: 30\n")
    return subprocess.run([sys.executable, "-m", "windowvo.run", str(cfg)], capture_output=True, text=True, timeout=300)


def test_loads_valid_sequence(seq):
    s = load_native(seq)
    assert len(s) == len(s.timestamps) > 100
    assert s.odometry is not None and s.odometry.synthetic
    assert s.groundtruth is not None and len(s.groundtruth) == len(s)
    assert s.warnings == []


def _break(seq: Path, how: str) -> None:
    imgs = sorted((seq / "images").iterdir())
    if how == "missing_folder":
        shutil.rmtree(seq)
    elif how == "empty_images":
        for p in imgs:
            p.unlink()
    elif how == "times_count":
        lines = (seq / "times.txt").read_text().splitlines()
        (seq / "times.txt").write_text("\n".join(lines[:-3]) + "\n")
    elif how == "times_order":
        lines = (seq / "times.txt").read_text().splitlines()
        lines[10], lines[11] = lines[11], lines[10]
        (seq / "times.txt").write_text("\n".join(lines) + "\n")
    elif how == "camera_malformed":
        (seq / "camera.yaml").write_text("width: 640\nheight: 480\nfx: -300\nfy: 300\ncx: 320\ncy: 240\nT_base_cam: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n")
    elif how == "camera_missing_key":
        (seq / "camera.yaml").write_text("width: 640\nheight: 480\nfx: 300\n")
    elif how == "camera_wrong_size":
        txt = (seq / "camera.yaml").read_text().replace("width: 640", "width: 800")
        (seq / "camera.yaml").write_text(txt)
    elif how == "odometry_no_overlap":
        rows = ["timestamp,x,y,yaw"] + [f"{1000 + i * 0.01:.3f},{i * 0.01},0,0" for i in range(100)]
        (seq / "odometry.csv").write_text("\n".join(rows) + "\n")
    elif how == "odometry_bad_header":
        (seq / "odometry.csv").write_text("t,x,y\n0,0,0\n")
    else:
        raise ValueError(how)


CASES = [
    ("missing_folder", SequenceError, "not found"),
    ("empty_images", SequenceError, "no images"),
    ("times_count", SequenceError, "timestamps but images/ has"),
    ("times_order", SequenceError, "not strictly increasing"),
    ("camera_malformed", CalibrationError, "focal"),
    ("camera_missing_key", CalibrationError, "missing key"),
    ("camera_wrong_size", CalibrationError, "camera.yaml says"),
    ("odometry_no_overlap", SequenceError, "does not overlap"),
    ("odometry_bad_header", SequenceError, "header"),
]


@pytest.mark.parametrize("how,exc,needle", CASES)
def test_bad_sequence_raises_clear_error(seq, how, exc, needle):
    _break(seq, how)
    with pytest.raises(exc, match=needle):
        load_native(seq)


@pytest.mark.parametrize("how", ["missing_folder", "empty_images", "times_order", "camera_malformed", "odometry_no_overlap"])
def test_cli_exit_code_2_without_traceback(seq, tmp_path, how):
    _break(seq, how)
    r = run_cli(seq, tmp_path / "out")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    err_lines = [ln for ln in r.stderr.splitlines() if ln.startswith("windowvo: error:")]
    assert len(err_lines) == 1


def test_partial_odometry_overlap_is_a_warning(seq):
    odo = read_odometry_csv(seq / "odometry.csv")
    keep = odo.timestamps <= odo.timestamps[-1] / 2
    rows = ["timestamp,x,y,yaw"] + [f"{t},{x},{y},{w}" for t, x, y, w in zip(odo.timestamps[keep], odo.x[keep], odo.y[keep], odo.yaw[keep])]
    (seq / "odometry.csv").write_text("\n".join(rows) + "\n")
    s = load_native(seq)
    assert any("odometry covers only" in w for w in s.warnings)


def test_unreadable_image_is_skipped_and_run_goes_on(seq, tmp_path):
    imgs = sorted((seq / "images").iterdir())
    imgs[12].write_bytes(b"not an image")
    r = run_cli(seq, tmp_path / "out")
    assert r.returncode == 0, r.stderr
    traj = read_tum(tmp_path / "out" / "trajectory.txt")
    assert len(traj) == 30  # one line per frame, the skipped one interpolated
    assert "unreadable" in r.stderr


def test_malformed_groundtruth_is_a_warning_not_a_stop(seq, tmp_path):
    """Ground truth only feeds the evaluation: a malformed last line warns, skips the
    evaluation, and the run still writes its trajectory (exit 0)."""
    with (seq / "groundtruth.txt").open("a") as fh:
        fh.write("12.345 1.0 2.0\n")
    s = load_native(seq)
    assert s.groundtruth is None
    assert any("ground truth ignored" in w and "expected 8 numbers" in w for w in s.warnings)
    r = run_cli(seq, tmp_path / "out")
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "ground truth ignored, no evaluation" in r.stderr and "groundtruth.txt:" in r.stderr
    assert len(read_tum(tmp_path / "out" / "trajectory.txt")) == 30
    assert "accuracy:" not in r.stdout


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.stack([make_T(rpy_to_R(*rng.uniform(-3, 3, 3)), rng.normal(size=3)) for _ in range(20)])
    ts = np.arange(20) * 0.1
    write_tum(tmp_path / "t.txt", ts, poses)
    back = read_tum(tmp_path / "t.txt")
    assert np.allclose(back.T_world_base, poses, atol=1e-6)


def test_featureless_sequence_is_a_clear_error(seq, tmp_path):
    import cv2

    for p in sorted((seq / "images").iterdir())[:30]:
        cv2.imwrite(str(p), np.full((480, 640), 128, np.uint8))
    r = run_cli(seq, tmp_path / "out")
    assert r.returncode == 2, r.stderr
    assert "no trackable features" in r.stderr and "Traceback" not in r.stderr
    assert (tmp_path / "out" / "stats.csv").is_file()


@pytest.mark.slow
def test_synth_and_eval_command_lines(tmp_path):
    out = tmp_path / "synth"
    r = subprocess.run([sys.executable, "-m", "windowvo.synth", str(out), "--path", "loop", "--duration", "1.0",
                        "--obstacles", "2", "--black-frames", "3"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    s = load_native(out)
    assert len(s) == 21 and s.odometry.synthetic and len(s.groundtruth) == 21
    import cv2

    assert cv2.imread(str(s.image_paths[3]), cv2.IMREAD_GRAYSCALE).max() == 0  # the black frame
    # An estimate 10% too large (positions scaled by 1.1 about the first one, same rotations).
    # Known answers for any non-straight path: a rigid alignment leaves 0.1 x the positions'
    # spread about their mean (ATE SE(3)); Sim(3) removes it with scale 1/1.1; after aligning
    # the first pose the end point is 0.1 x |p_end - p_0| off.
    gt = s.groundtruth
    p = gt.positions
    est = gt.T_world_base.copy()
    est[:, :3, 3] = p[0] + 1.1 * (p - p[0])
    write_tum(tmp_path / "est.txt", gt.timestamps, est)
    e = subprocess.run([sys.executable, "-m", "windowvo.eval", str(out / "groundtruth.txt"), str(tmp_path / "est.txt"),
                        "--json"], capture_output=True, text=True, timeout=300)
    assert e.returncode == 0, e.stderr
    import json

    rep = json.loads(e.stdout)
    assert rep["n_poses"] == 21
    spread = float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
    assert rep["ate_se3_rmse_m"] == pytest.approx(0.1 * spread, abs=2e-6)
    assert rep["sim3_scale"] == pytest.approx(1.0 / 1.1, abs=1e-4)
    assert rep["ate_sim3_rmse_m"] == pytest.approx(0.0, abs=2e-6)
    end = 0.1 * float(np.linalg.norm(p[-1] - p[0]))
    assert rep["end_drift_pct"] == pytest.approx(100.0 * end / gt.path_length(), abs=1e-3)
    bad = subprocess.run([sys.executable, "-m", "windowvo.eval", str(out / "nope.txt"), str(out / "groundtruth.txt")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_wheel_distance_sums_the_samples_strictly_between_the_two_times():
    """``WheelOdometry.distance`` against the path length written out sample by sample: the interpolated ends
    and every sample strictly inside, also when an end falls exactly on a sample or both ends in one gap."""
    import numpy as np

    from windowvo.io.odometry import WheelOdometry

    rng = np.random.default_rng(3)
    ts = np.cumsum(rng.uniform(0.005, 0.02, 400))
    w = WheelOdometry(ts, np.cumsum(rng.normal(0, 0.01, 400)), np.cumsum(rng.normal(0, 0.01, 400)), np.zeros(400))
    for t0, t1 in [(ts[10], ts[50]), (ts[10] + 1e-4, ts[50] - 1e-4), (ts[20] + 1e-4, ts[20] + 2e-4),
                   (ts[0] - 1.0, ts[5]), *(sorted(rng.uniform(ts[0], ts[-1], 2)) for _ in range(50))]:
        inside = (ts > t0) & (ts < t1)
        p0, p1 = w.pose_at(t0)[:2, 3], w.pose_at(t1)[:2, 3]
        pts = np.vstack([p0, np.stack([w.x[inside], w.y[inside]], axis=1), p1])
        assert w.distance(t0, t1) == np.sum(np.hypot(*np.diff(pts, axis=0).T))


def test_wheel_pose_is_np_interp_of_x_y_and_yaw_to_the_bit():
    """``WheelOdometry.pose_at`` interpolates x, y and yaw with one binary search: the same doubles as three
    ``np.interp`` calls, inside, on every sample, before the first and past the last (clamped), and for nan."""
    import numpy as np

    from windowvo.geometry import planar_T
    from windowvo.io.odometry import WheelOdometry

    rng = np.random.default_rng(5)
    for n in (1, 2, 300):
        ts = np.cumsum(rng.uniform(1e-4, 0.05, n)) - 2.0
        x, y, yaw = (np.cumsum(rng.normal(0.0, 1.0, n)) * scale for scale in (1e-3, 1.0, 1e3))
        w = WheelOdometry(ts, x, y, yaw)
        for t in [*rng.uniform(ts[0] - 1.0, ts[-1] + 1.0, 500), *ts, float("nan")]:
            expected = planar_T(*(float(np.interp(t, ts, v)) for v in (x, y, yaw)))
            assert np.array_equal(w.pose_at(float(t)), expected, equal_nan=True), (n, t)
