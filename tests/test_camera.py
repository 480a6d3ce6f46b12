import numpy as np
import pytest

from windowvo.camera import CameraModel
from windowvo.errors import CalibrationError

MODELS = [
    ("none", ()),
    ("radtan", (-0.28, 0.07, 0.001, -0.0005, 0.01)),
    ("equidistant", (0.05, -0.01, 0.002, -0.0005)),
]


@pytest.mark.parametrize("model,dist", MODELS)
def test_project_unproject_round_trip(model, dist):
    cam = CameraModel(640, 480, 360.0, 355.0, 321.0, 238.0, model, dist)
    rng = np.random.default_rng(0)
    uv = rng.uniform([20, 20], [620, 460], (400, 2))
    rays = cam.unproject(uv)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    assert np.abs(cam.project(rays * 3.7) - uv).max() < 1e-6


@pytest.mark.parametrize("model,dist", MODELS)
def test_point_round_trip_and_undistort(model, dist):
    cam = CameraModel(640, 480, 360.0, 360.0, 320.0, 240.0, model, dist)
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(1.5, 6, 200)]
    uv = cam.project(p)
    xn = cam.undistort_normalized(uv)
    assert np.abs(xn - p[:, :2] / p[:, 2:3]).max() < 1e-8
    # undistorted pixels are what a pinhole camera with the same K sees
    ideal = p[:, :2] / p[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    assert np.abs(cam.undistort_pixels(uv) - ideal).max() < 1e-6


def test_distortion_changes_pixels():
    a = CameraModel(640, 480, 360, 360, 320, 240)
    b = CameraModel(640, 480, 360, 360, 320, 240, "radtan", (-0.3, 0.1, 0, 0))
    p = np.array([[1.0, 0.8, 2.0]])
    assert np.linalg.norm(a.project(p) - b.project(p)) > 5.0


@pytest.mark.parametrize(
    "kw,msg",
    [
        (dict(fx=-1.0), "focal"),
        (dict(width=0), "width"),
        (dict(cx=900.0), "principal point"),
        (dict(distortion_model="radtan", distortion=(0.1,)), "radtan"),
        (dict(distortion_model="equidistant", distortion=(0.1, 0, 0)), "equidistant"),
        (dict(T_base_cam=np.diag([1.0, 1.0, 2.0, 1.0])), "rigid"),
    ],
)
def test_bad_calibration_is_rejected(kw, msg):
    args = dict(width=640, height=480, fx=300.0, fy=300.0, cx=320.0, cy=240.0)
    args.update(kw)
    with pytest.raises(CalibrationError, match=msg):
        CameraModel(**args)
