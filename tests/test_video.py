"""Video files as input: an MJPG .avi written from a rendered loop, run end to end."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import make_config

from windowvo.io.sequence import load_native, read_camera_yaml
from windowvo.io.video import beside, load_video
from windowvo.runtime.job import run_job


def _camera_section(native: Path) -> dict:
    cam = read_camera_yaml(native / "camera.yaml").to_dict()
    return {k: cam[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion",
                                "T_base_cam")}


def _write_video(native: Path, path: Path, fourcc: str = "MJPG", fps: float = 20.0, n: int | None = None) -> Path:
    images = sorted((native / "images").iterdir())[:n]
    first = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (first.shape[1], first.shape[0]),
                        isColor=False)
    assert w.isOpened(), f"OpenCV cannot write {fourcc}"
    for p in images:
        w.write(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
    w.release()
    return path


@pytest.fixture(scope="module")
def video(short_loop, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("video")
    path = _write_video(short_loop, d / "drive.avi")
    shutil.copy(short_loop / "odometry.csv", d / "drive.odometry.csv")  # same stem: this video's wheels
    shutil.copy(short_loop / "groundtruth.txt", d / "groundtruth.txt")  # folder-wide fallback name
    return path


def test_video_runs_end_to_end(short_loop, video, tmp_path):
    nat = load_native(short_loop)
    cfg = make_config(video, tmp_path / "out", dataset="video", camera=_camera_section(short_loop))
    rep = run_job(cfg)
    seq = rep.sequence
    assert len(seq) == len(nat) and rep.result.n_frames == len(nat)
    # container timestamps (20 fps), seconds from the first frame: the native clock
    assert np.allclose(seq.timestamps, nat.timestamps, atol=1e-3)
    assert seq.odometry is not None and seq.groundtruth is not None and len(seq.groundtruth) == len(nat)
    # MJPG is lossy but close to the rendered frames
    assert np.abs(seq.read_image(10).astype(int) - nat.read_image(10)).mean() < 3.0
    # metric: like the rendered regression runs, a third of the wheel-only error at most
    assert rep.accuracy.ate_se3_rmse_m <= rep.wheel_accuracy.ate_se3_rmse_m / 3.0, (rep.accuracy, rep.wheel_accuracy)
    assert rep.accuracy.ate_se3_rmse_m < 0.1


def test_frames_stream_forward_and_rewind(short_loop, tmp_path):
    nat = load_native(short_loop)
    path = _write_video(short_loop, tmp_path / "v.mkv", fourcc="FFV1", n=30)  # lossless: exact pixels
    seq = load_video(path, make_config(path, tmp_path, camera=_camera_section(short_loop)).camera, 20.0)
    for i in (0, 1, 7, 29):
        assert np.array_equal(seq.read_image(i), nat.read_image(i))
    restarts = seq.source.restarts
    assert np.array_equal(seq.read_image(3), nat.read_image(3))  # earlier frame: the reader reopens
    assert seq.source.restarts == restarts + 1
    seq.close()


def test_odometry_beside_the_video(tmp_path):
    v = tmp_path / "a.mp4"
    v.write_bytes(b"")
    (tmp_path / "odometry.csv").write_text("x")
    assert beside(v, "odometry.csv") == tmp_path / "odometry.csv"
    (tmp_path / "a.odometry.csv").write_text("x")
    assert beside(v, "odometry.csv") == tmp_path / "a.odometry.csv"  # the video's own file wins
    assert beside(v, "groundtruth.txt") is None


def _run(tmp: Path, video: Path, camera: dict) -> subprocess.CompletedProcess:
    import yaml

    cfg = tmp / "c.yaml"
    cfg.write_text(yaml.safe_dump({"sequence": str(video), "output": str(tmp / "out"), "dataset": "video",
                                   "progress": False, "viz": {"rerun": "off"}, "camera": camera}))
    return subprocess.run([sys.executable, "-m", "windowvo.run", str(cfg)], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("case", ["missing", "garbage", "no_frames"])
def test_bad_video_gives_one_line_and_exit_2(short_loop, tmp_path, case):
    cam = _camera_section(short_loop)
    path = tmp_path / "bad.avi"
    if case == "garbage":
        path.write_bytes(np.random.default_rng(0).integers(0, 255, 50_000, dtype=np.uint8).tobytes())
    elif case == "no_frames":
        w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (cam["width"], cam["height"]),
                            isColor=False)
        w.release()
    r = _run(tmp_path, path, cam)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("windowvo: error:")]
    assert len(errors) == 1, r.stderr
    expect = {"missing": "video file not found", "garbage": "cannot open video", "no_frames": "no frames"}[case]
    assert expect in errors[0], errors[0]
