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


# A fisheye wider than 180 degrees: 640x480 with f = 200 px sees 2 rad (115 deg) off-axis in the corners.
FISHEYE = dict(width=640, height=480, fx=200.0, fy=200.0, cx=320.0, cy=240.0, distortion_model="equidistant")


def test_pure_equidistant_bearings_beyond_90_degrees():
    """With zero coefficients the lens maps off-axis angle theta to radius f * theta: known answers."""
    cam = CameraModel(**FISHEYE, distortion=(0.0, 0.0, 0.0, 0.0))
    theta = np.radians([0.0, 30.0, 89.0, 100.0, 114.0])
    phi = np.radians([0.0, 45.0, 180.0, -60.0, 210.0])  # azimuth in the image
    uv = np.c_[320.0 + 200.0 * theta * np.cos(phi), 240.0 + 200.0 * theta * np.sin(phi)]
    expected = np.c_[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]
    assert np.abs(cam.unproject(uv) - expected).max() < 1e-12
    assert np.abs(np.degrees(cam.ray_angle(uv)) - [0.0, 30.0, 89.0, 100.0, 114.0]).max() < 1e-9
    # and back: points beside and behind the lens plane project to the right pixels
    assert np.abs(cam.project(expected * 2.5) - uv).max() < 1e-9


def test_fisheye_round_trip_over_the_whole_image():
    cam = CameraModel(**FISHEYE, distortion=(-0.01, 0.003, -0.0005, 0.00003))
    uv = cam.pixel_grid()[::97]
    b = cam.unproject(uv)
    assert np.allclose(np.linalg.norm(b, axis=1), 1.0)
    assert (b[:, 2] < 0).sum() > 100  # the corners look behind the lens plane
    assert np.abs(cam.project(b * 4.0) - uv).max() < 1e-6
    # rays at 90 degrees or more have no pinhole coordinates; the others agree with the bearings
    xn = cam.undistort_normalized(uv)
    behind = b[:, 2] <= 0
    assert np.all(np.isnan(xn[behind]))
    assert np.abs(xn[~behind] - b[~behind, :2] / b[~behind, 2:3]).max() < 1e-6


def test_equidistant_with_zero_coefficients_is_still_a_fisheye():
    fish = CameraModel(**FISHEYE, distortion=(0.0, 0.0, 0.0, 0.0))
    assert fish.has_distortion
    # a point 60 deg off-axis: fisheye radius f * theta, not the pinhole's f * tan(theta)
    uv = fish.project(np.array([[np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))]]))
    assert abs(uv[0, 0] - 320.0 - 200.0 * np.radians(60)) < 1e-9


@pytest.mark.parametrize("model,dist", MODELS[1:])
def test_undistortion_jacobian_matches_finite_differences(model, dist):
    """The analytic-by-inversion Jacobian against differences of the iterative undistortion."""
    cam = CameraModel(640, 480, 360.0, 355.0, 321.0, 238.0, model, dist)
    uv = np.random.default_rng(2).uniform([20, 20], [620, 460], (100, 2))
    J = cam.undistortion_jacobian(uv)
    h = 1e-3
    num = np.stack([(cam.undistort_pixels(uv + d) - cam.undistort_pixels(uv - d)) / (2 * h)
                    for d in (np.array([h, 0.0]), np.array([0.0, h]))], axis=2)
    assert np.abs(J - num).max() < 1e-5


def test_fisheye_noise_stretch_is_one_over_cos_squared():
    """Pure equidistant: the pinhole radius f tan(theta) of distorted radius f theta grows as 1/cos^2."""
    cam = CameraModel(**FISHEYE, distortion=(0.0, 0.0, 0.0, 0.0))
    theta = np.radians([10.0, 45.0, 70.0, 80.0])
    uv = np.c_[320.0 + 200.0 * theta, np.full(4, 240.0)]  # along the x axis: radial = du
    J = cam.undistortion_jacobian(uv)
    assert np.allclose(J[:, 0, 0], 1.0 / np.cos(theta) ** 2, rtol=1e-6)
    assert np.allclose(J[:, 1, 1], np.tan(theta) / theta, rtol=1e-6)  # tangential stretch
    assert np.allclose(J[:, 0, 1], 0.0, atol=1e-6)
    assert np.all(np.isnan(cam.undistortion_jacobian(np.array([[320.0 + 200.0 * np.radians(95.0), 240.0]]))))
