"""The street and warehouse scenes, the wheels' yaw scale error and the synth command line's bag output.

Geometry is checked by ray casting: the range buffer puts every pixel's surface point in the world,
where kerbs, pavements and markings must stand at their heights and the camera at its own.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from windowvo.config import RosbagConfig
from windowvo.io.odometry import read_odometry_csv
from windowvo.io.rosbag import load_rosbag
from windowvo.io.sequence import list_images, read_camera_yaml
from windowvo.io.trajectory import read_tum
from windowvo.synth import bagwriter
from windowvo.synth.__main__ import main as synth_main
from windowvo.synth.generate import SynthSpec, WheelErrorModel, build_world, simulate_wheel_odometry
from windowvo.synth.paths import PathKind
from windowvo.synth.scene import Renderer
from windowvo.synth.scenes import PAINT_LIFT_M, STREET, SceneKind

SMALL = dict(width=160, height=120, fx=85.0)
SMALL_ARGS = ["--width", "160", "--height", "120", "--fx", "85"]
KERB_M = 0.15


def _surface(world, t: float):
    """Image, world points and the camera pose of every pixel seen at time t (nan: nothing)."""
    cam = world.camera
    r = Renderer(world.scene, cam)
    T_wc = world.T_world_base(t) @ cam.T_base_cam
    img, range_m = r.render(T_wc, t)
    d = cam.pixel_bearings() @ T_wc[:3, :3].T
    p = T_wc[:3, 3] + range_m.reshape(-1, 1) * d
    p[~np.isfinite(range_m.ravel())] = np.nan
    return img.ravel(), p, T_wc


@pytest.fixture(scope="module")
def street():
    world = build_world(SynthSpec.for_scene(SceneKind.STREET, duration_s=3.0, kerb_height_m=KERB_M, n_obstacles=0,
                                                **SMALL))  # no parked cars: their sides would cross every height
    return world, *_surface(world, 1.0)


def _lateral(world, p: np.ndarray) -> np.ndarray:
    """Signed offset (left positive) of world points from the path, near the camera (the path runs along x)."""
    _x, y, _yaw = world.planar.at(p[:, 0])
    return p[:, 1] - y


def test_street_camera_is_1_65_m_above_the_road(street):
    world, _img, p, T_wc = street
    assert T_wc[2, 3] == pytest.approx(1.65, abs=1e-9)
    assert world.T_world_base(2.0)[2, 3] == pytest.approx(0.0, abs=1e-12)  # the base drives on the road
    on_road = np.abs(p[:, 2]) < 1e-3
    assert on_road.mean() > 0.2  # the lower image is road


def test_street_kerbs_and_pavements_stand_at_their_height_beside_the_road(street):
    world, _img, p, T_wc = street
    near = np.hypot(p[:, 0] - T_wc[0, 3], p[:, 1] - T_wc[1, 3]) < 25.0
    lat = _lateral(world, p)
    right_kerb = -(STREET.lane_w / 2 + STREET.parking_w)  # the robot drives in the right lane
    left_kerb = STREET.lane_w * 1.5 + STREET.parking_w
    top = near & (np.abs(p[:, 2] - KERB_M) < 1e-3)  # pavement tops
    assert top.sum() > 50
    assert (lat[top] < 0).sum() > 10 and (lat[top] > 0).sum() > 10  # on both sides
    # pavements lie beyond the kerbs only (a little slack: the path sways 0.3 m around the lane's centre)
    assert np.all((lat[top] < right_kerb + 0.35) | (lat[top] > left_kerb - 0.35))
    # the kerb faces: points between road and pavement height, at a kerb's offset
    face = near & (p[:, 2] > 0.01) & (p[:, 2] < KERB_M - 0.01)
    assert face.sum() > 3
    kerb_dist = np.minimum(np.abs(lat[face] - right_kerb), np.abs(lat[face] - left_kerb))
    assert np.all(kerb_dist < 0.35)
    # the road between the kerbs: flat at z = 0 (or the markings on it)
    road = near & (lat > right_kerb + 0.35) & (lat < left_kerb - 0.35) & (p[:, 2] < 1.0)
    assert road.sum() > 200 and np.all(p[road, 2] < PAINT_LIFT_M + 1e-3)


def test_street_lane_markings_are_brighter_than_the_asphalt(street):
    _world, img, p, _T = street
    paint = np.abs(p[:, 2] - PAINT_LIFT_M) < 5e-4
    asphalt = np.abs(p[:, 2]) < 5e-4
    assert paint.sum() > 20 and asphalt.sum() > 1000
    assert np.median(img[paint]) > np.median(img[asphalt]) + 0.3
    # low-contrast asphalt: a narrower spread than the pavement's slabs
    pavement = np.abs(p[:, 2] - KERB_M) < 1e-3
    assert np.std(img[asphalt]) < np.std(img[pavement])


def test_street_follows_a_gentle_curve():
    """path=loop on the street is a curve of 80 m radius, and the road (with its markings) follows it."""
    world = build_world(SynthSpec.for_scene(SceneKind.STREET, path=PathKind.LOOP, duration_s=12.0, **SMALL))
    x, y, yaw = world.planar.at(np.array([0.0, 12.0]))
    assert np.hypot(x, y) == pytest.approx([80.0, 80.0], abs=1e-6)  # on the circle around the origin
    assert 1.0 < yaw[1] - yaw[0] < 2.0  # 120 m of arc: a turn of 1.5 rad
    _img, p, T_wc = _surface(world, 6.0)
    near = np.hypot(p[:, 0] - T_wc[0, 3], p[:, 1] - T_wc[1, 3]) < 25.0  # (beyond the path's end it runs straight)
    paint = near & (np.abs(p[:, 2] - PAINT_LIFT_M) < 5e-4)
    assert paint.sum() > 20
    # markings lie on circles about the same centre: the lane lines 3.5 m either side of the road's centre
    # line, which runs 1.75 m inside the path (a left turn, the robot in the right lane)
    r_paint = np.hypot(p[paint, 0], p[paint, 1])
    centre = 80.0 - STREET.lane_w / 2
    off = np.abs(r_paint[:, None] - (centre + np.array([-STREET.lane_w, 0.0, STREET.lane_w]))[None, :])
    on_line = off.min(axis=1) < 0.3
    assert on_line.mean() > 0.9  # (a few points low on the kerb faces share the paint's height)
    assert np.all(np.bincount(off[on_line].argmin(axis=1), minlength=3) > 0)  # both lane lines and the dashes


@pytest.fixture(scope="module")
def warehouse():
    return build_world(SynthSpec.for_scene(SceneKind.WAREHOUSE, duration_s=10.0, **SMALL))


def test_warehouse_camera_height_and_floor(warehouse):
    T_wc = warehouse.T_world_base(3.0) @ warehouse.camera.T_base_cam
    assert T_wc[2, 3] == pytest.approx(0.4, abs=1e-9)
    _img, p, _T = _surface(warehouse, 3.0)
    floor = np.abs(p[:, 2]) < 1e-3
    assert floor.mean() > 0.2 and np.nanmin(p[:, 2]) > -1e-3  # the floor, at z = 0, and nothing below it
    assert np.nanmax(p[:, 2]) > 3.0  # tall racks in view
    assert warehouse.scene.planes[0].gloss > 0  # the floor shines


def test_warehouse_person_walks(warehouse):
    """The one person crosses the path: seen from a fixed pose, the picture changes over time, and only
    where the person is (a scene without them renders the same at both times)."""
    person = warehouse.scene.moving
    assert len(person) == 1
    c0, c1 = (np.mean([p.origin for p in person[0].planes_at(t)], axis=0) for t in (0.0, 2.0))
    assert np.hypot(*(c1 - c0)[:2]) > 1.0
    cam = warehouse.camera
    mid = 0.5 * (np.asarray(person[0].start_xy) + np.asarray(person[0].end_xy))
    T_wb = warehouse.T_world_base(0.0).copy()
    heading = np.arctan2(*(mid - T_wb[:2, 3])[::-1])
    T_wb[:3, :3] = np.array([[np.cos(heading), -np.sin(heading), 0], [np.sin(heading), np.cos(heading), 0], [0, 0, 1]])
    T_wc = T_wb @ cam.T_base_cam
    r = Renderer(warehouse.scene, cam)
    ranges = [r.render(T_wc, t)[1] for t in np.linspace(0.0, person[0].period_s / 2, 4)]
    ranges = [np.where(np.isfinite(rg), rg, 1e3) for rg in ranges]
    changed = [np.mean(np.abs(a - b) > 0.05) for a, b in itertools.pairwise(ranges)]
    assert max(changed) > 0.005
    warehouse.scene.moving = []
    try:
        still = [r.render(T_wc, t)[1] for t in (0.0, person[0].period_s / 2)]
    finally:
        warehouse.scene.moving = person
    assert np.array_equal(still[0], still[1])


@pytest.mark.parametrize("scale", [0.03, -0.05])
def test_yaw_scale_error_scales_the_yaw_increments(scale):
    world = build_world(SynthSpec(path=PathKind.LOOP, duration_s=6.0, n_obstacles=0, **SMALL))
    err = WheelErrorModel(scale_error=0.0, yaw_bias_per_m=0.0, distance_noise=0.0, yaw_noise=0.0,
                          yaw_scale_error=scale)
    odo = simulate_wheel_odometry(world, err, 0, "t")
    true_yaw = world.planar.at(odo.timestamps)[2]
    d_true = np.diff(true_yaw)
    d_odo = np.diff(odo.yaw)
    turning = np.abs(d_true) > 1e-4
    assert turning.sum() > 100
    assert np.allclose(d_odo[turning] / d_true[turning], 1.0 + scale, rtol=1e-9)
    assert f"yaw_scale_error={scale}" in odo.comment


def test_yaw_scale_error_on_the_command_line(tmp_path):
    out = tmp_path / "seq"
    assert synth_main([str(out), "--duration", "2", "--odo-yaw-scale-error", "0.03", "--odo-noise", "0",
                       "--odo-yaw-bias", "0", "--odo-scale-error", "0", *SMALL_ARGS]) == 0
    odo = read_odometry_csv(out / "odometry.csv")
    gt = read_tum(out / "groundtruth.txt")
    R = gt.T_world_base[:, :3, :3]
    gt_yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    odo_yaw = np.interp(gt.timestamps, odo.timestamps, odo.yaw)
    ratio = (odo_yaw[-1] - odo_yaw[0]) / (gt_yaw[-1] - gt_yaw[0])
    assert ratio == pytest.approx(1.03, abs=1e-4)
    assert "yaw_scale_error=0.03" in (out / "odometry.csv").read_text().splitlines()[0]


def test_scene_defaults_and_overrides_on_the_command_line(tmp_path):
    assert synth_main([str(tmp_path / "s"), "--scene", "street", "--duration", "1", *SMALL_ARGS]) == 0
    assert synth_main([str(tmp_path / "w"), "--scene", "warehouse", "--duration", "0.5", "--camera-height", "0.3",
                       *SMALL_ARGS]) == 0
    assert read_camera_yaml(tmp_path / "s" / "camera.yaml").T_base_cam[2, 3] == pytest.approx(1.65)
    times = np.loadtxt(tmp_path / "s" / "times.txt")
    assert np.allclose(np.diff(times), 0.1)  # 10 Hz
    gt = read_tum(tmp_path / "s" / "groundtruth.txt")
    speed = np.linalg.norm(np.diff(gt.T_world_base[:, :3, 3], axis=0), axis=1) / np.diff(gt.timestamps)
    assert speed.min() >= 8.0 and speed.max() <= 14.0
    assert read_camera_yaml(tmp_path / "w" / "camera.yaml").T_base_cam[2, 3] == pytest.approx(0.3)


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_bag_output_is_read_back_by_the_rosbag_loader(tmp_path, fmt, capsys):
    out = tmp_path / "seq"
    assert synth_main([str(out), "--duration", "1", "--dropped-frames", "4", *SMALL_ARGS, "--bag", fmt]) == 0
    bag = bagwriter.bag_path_beside(out, bagwriter.BagFormat(fmt))
    assert bag.exists() and str(bag) in capsys.readouterr().out
    seq = load_rosbag(bag, RosbagConfig(), None)
    n = len(list_images(out / "images"))
    assert n == 20 and len(seq) == n
    assert seq.odometry is not None and seq.groundtruth is not None and len(seq.groundtruth) == n
    assert seq.camera.width == 160 and seq.camera.fx == 85.0


def test_bagwriter_converts_a_native_folder(tmp_path):
    out = tmp_path / "seq"
    assert synth_main([str(out), "--duration", "0.5", *SMALL_ARGS]) == 0
    assert bagwriter.main([str(out), str(tmp_path / "conv"), "--format", "ros2"]) == 0
    assert len(load_rosbag(tmp_path / "conv", RosbagConfig(), None)) == 11


def _one_line_error(capsys, fn, argv) -> str:
    try:
        rc = fn(argv)
    except SystemExit as e:  # argparse's own checks
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("args,message", [
    (["--odo-yaw-scale-error", "-2"], "yaw_scale_error must lie in (-0.5, 0.5)"),
    (["--odo-yaw-scale-error", "abc"], "invalid float value: 'abc'"),
    (["--scene", "street", "--path", "figure_eight"], "the street scene drives the paths"),
    (["--scene", "warehouse", "--ramp-height", "0.3"], "ramps exist in the room scene only"),
    (["--scene", "forest"], "invalid choice: 'forest'"),
    (["--camera-height", "-1"], "camera_height_m must be positive"),
    (["--bag", "zip"], "invalid choice: 'zip'"),
])
def test_bad_synth_values_are_one_line(tmp_path, capsys, args, message):
    line = _one_line_error(capsys, synth_main, [str(tmp_path / "out"), *args])
    assert line.startswith("windowvo: error: ") and message in line
    assert not (tmp_path / "out").exists()


def test_bag_output_that_exists_is_refused_before_rendering(tmp_path, capsys):
    (tmp_path / "seq.bag").write_text("mine")
    line = _one_line_error(capsys, synth_main, [str(tmp_path / "seq"), "--bag", "ros1", *SMALL_ARGS])
    assert "exists already" in line and not (tmp_path / "seq").exists()
    assert (tmp_path / "seq.bag").read_text() == "mine"


def test_bagwriter_bad_input_is_one_line(tmp_path, capsys):
    line = _one_line_error(capsys, bagwriter.main, [str(tmp_path / "nothing"), str(tmp_path / "b.bag"), "--format", "ros1"])
    assert line.startswith("windowvo.synth.bagwriter: error: ") and "not a native sequence folder" in line
    line = _one_line_error(capsys, bagwriter.main, [str(tmp_path), str(tmp_path / "b"), "--format", "zip"])
    assert "invalid choice" in line
