"""The renderer's geometry: the same floor point looks the same from two poses, for every lens;
ranges match the known floor geometry."""

import numpy as np
import pytest

from windowvo.geometry import inv_T
from windowvo.synth.generate import (
    KERB_CLEARANCE_M,
    KERB_SIDE_M,
    LensPreset,
    SynthSpec,
    build_world,
    lens_fields,
    place_kerbs,
)
from windowvo.synth.paths import PathKind
from windowvo.synth.scene import Renderer

LENSES = list(LensPreset)


@pytest.mark.parametrize("lens", LENSES)
def test_floor_points_are_photometrically_consistent(lens):
    world = build_world(SynthSpec(path=PathKind.LOOP, duration_s=10.0, seed=2, **lens_fields(lens)))
    cam = world.camera
    r = Renderer(world.scene, cam)
    T0 = world.T_world_base(2.0) @ cam.T_base_cam
    T1 = world.T_world_base(2.3) @ cam.T_base_cam
    img0, _ = r.render(T0, 2.0)
    img1, _ = r.render(T1, 2.3)
    rng = np.random.default_rng(0)
    uv0 = rng.uniform([40, 280], [600, 400], (400, 2))  # lower image: the floor
    p_world = r.surface_points(T0, uv0, 2.0)
    on_floor = np.abs(p_world[:, 2]) < 1e-3
    assert on_floor.mean() > 0.8
    T_c1_w = inv_T(T1)
    pc1 = p_world[on_floor] @ T_c1_w[:3, :3].T + T_c1_w[:3, 3]
    uv1 = cam.project(pc1)
    inside = cam.in_image(uv1, margin=3) & (pc1[:, 2] > 0.2)
    assert inside.sum() > 100

    def bilinear(img, uv):
        x, y = uv[:, 0], uv[:, 1]
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        ax, ay = x - x0, y - y0
        return ((1 - ax) * (1 - ay) * img[y0, x0] + ax * (1 - ay) * img[y0, x0 + 1]
                + (1 - ax) * ay * img[y0 + 1, x0] + ax * ay * img[y0 + 1, x0 + 1])

    a = bilinear(img0, uv0[on_floor][inside])
    b = bilinear(img1, uv1[inside])
    # Same texture under both poses: small photometric error, far below that of random pairs.
    err = np.median(np.abs(a - b))
    shuffled = np.median(np.abs(a - rng.permutation(b)))
    assert err < 0.02, err
    assert shuffled > 5 * err
    if lens is LensPreset.FISHEYE:  # the checked floor points include rays far off the axis
        assert np.degrees(cam.ray_angle(uv0[on_floor])).max() > 60.0


@pytest.mark.parametrize("lens", LENSES)
def test_range_buffer_matches_the_floor_geometry(lens):
    """In a room without obstacles every downward ray ends on the floor (z = 0) at the known range
    h / (-d_z) from a camera at height h along the unit world direction d, walls permitting."""
    world = build_world(SynthSpec(path=PathKind.LOOP, duration_s=10.0, seed=2, n_obstacles=0, **lens_fields(lens)))
    cam = world.camera
    r = Renderer(world.scene, cam)
    T_wc = world.T_world_base(3.0) @ cam.T_base_cam
    _img, range_m = r.render(T_wc, 3.0)
    d_world = cam.pixel_bearings() @ T_wc[:3, :3].T
    h = T_wc[2, 3]
    with np.errstate(divide="ignore"):
        expected = np.where(d_world[:, 2] < -1e-3, h / -d_world[:, 2], np.inf)
    p_floor = T_wc[:3, 3] + expected[:, None] * d_world
    planes = world.scene.planes
    half_x, half_y = planes[0].length_u / 2, planes[0].length_v / 2  # the floor spans the room
    # well inside the room (a wall could not be in front) and not too grazing
    inside = (np.abs(p_floor[:, 0]) < half_x - 0.5) & (np.abs(p_floor[:, 1]) < half_y - 0.5) & (expected < 6.0)
    inside &= r.valid.ravel()
    got = range_m.ravel()
    assert inside.sum() > 0.3 * inside.size
    assert np.abs(got[inside] - expected[inside]).max() < 1e-3 * expected[inside].max()
    # upward rays end on a wall (|x| or |y| at the room's half size, below the wall top) or on nothing
    up = d_world[:, 2] > 0.05
    hit = up & np.isfinite(got)
    assert hit.sum() > 1000 and (up & ~hit).sum() > 1000  # walls and the open space above them
    p_hit = T_wc[:3, 3] + got[hit, None] * d_world[hit]
    on_wall = (np.abs(np.abs(p_hit[:, 0]) - half_x) < 0.01) | (np.abs(np.abs(p_hit[:, 1]) - half_y) < 0.01)
    assert np.all(on_wall) and np.all(p_hit[:, 2] <= 3.0 + 1e-3)
    if lens is LensPreset.FISHEYE:  # the check reaches rays beside and behind the lens plane
        assert np.degrees(cam.ray_angle(cam.pixel_grid()[inside])).max() > 90.0


def test_rendering_is_deterministic():
    w = build_world(SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=5.0, seed=4))
    r = Renderer(w.scene, w.camera)
    T = w.T_world_base(1.0) @ w.camera.T_base_cam
    a, _ = r.render(T, 1.0)
    b, _ = Renderer(build_world(SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=5.0, seed=4)).scene, w.camera).render(T, 1.0)
    assert np.array_equal(a, b)
    assert a.std() > 0.05  # textured, not flat


def test_a_calibration_error_changes_camera_yaml_only(tmp_path):
    """calib_pitch_error_deg: camera.yaml claims a camera pitched that much further down; the images and
    the ground truth are those of the true mount."""
    from windowvo.io.sequence import read_camera_yaml
    from windowvo.synth.generate import camera_for, generate_sequence

    spec = SynthSpec(path=PathKind.LOOP, duration_s=0.3, seed=3, width=160, height=120, fx=85.0)
    wrong = SynthSpec(path=PathKind.LOOP, duration_s=0.3, seed=3, width=160, height=120, fx=85.0,
                      calib_pitch_error_deg=1.0)
    generate_sequence(tmp_path / "true", spec)
    generate_sequence(tmp_path / "wrong", wrong)
    T_true = read_camera_yaml(tmp_path / "true" / "camera.yaml").T_base_cam
    T_claimed = read_camera_yaml(tmp_path / "wrong" / "camera.yaml").T_base_cam
    assert np.allclose(T_true, camera_for(spec).T_base_cam)
    R_rel = T_true[:3, :3].T @ T_claimed[:3, :3]  # in the camera frame: a rotation about its x axis
    angle = np.degrees(np.arccos(np.clip((np.trace(R_rel) - 1) / 2, -1, 1)))
    assert angle == pytest.approx(1.0, abs=1e-6) and abs(R_rel[0, 0] - 1.0) < 1e-12
    # looking further down: the claimed optical axis (base frame) points lower than the true one
    assert T_claimed[2, 2] < T_true[2, 2]
    assert np.allclose(T_claimed[:3, 3], T_true[:3, 3])
    assert (tmp_path / "true" / "groundtruth.txt").read_text() == (tmp_path / "wrong" / "groundtruth.txt").read_text()
    for a, b in zip(sorted((tmp_path / "true" / "images").iterdir()), sorted((tmp_path / "wrong" / "images").iterdir())):
        assert a.read_bytes() == b.read_bytes()


def test_floor_hidden_frames_blank_the_view_below_the_horizon(tmp_path):
    """floor_hidden_frames: the first N frames are one flat grey below the horizon of the base frame (for a
    camera pitched down, a band of rows at the bottom), the rest as rendered."""
    import cv2

    from windowvo.synth.generate import camera_for, generate_sequence

    kw = dict(path=PathKind.LOOP, duration_s=0.3, seed=3, width=160, height=120, fx=85.0)
    generate_sequence(tmp_path / "plain", SynthSpec(**kw))
    generate_sequence(tmp_path / "hidden", SynthSpec(**kw, floor_hidden_frames=2))
    cam = camera_for(SynthSpec(**kw))
    pitch = np.arcsin(-cam.T_base_cam[2, 2])  # optical axis below the horizontal
    horizon_row = cam.cy - cam.fy * np.tan(pitch)
    assert 0 < horizon_row < cam.height
    for i in range(4):
        plain = cv2.imread(str(tmp_path / "plain" / "images" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        hidden = cv2.imread(str(tmp_path / "hidden" / "images" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        below = hidden[int(horizon_row) + 2:]
        if i < 2:
            assert below.std() == 0.0 and plain[int(horizon_row) + 2:].std() > 5.0  # the floor was textured
            assert np.array_equal(hidden[: int(horizon_row) - 1], plain[: int(horizon_row) - 1])
        else:
            assert np.array_equal(hidden, plain)


def test_kerbs_stand_beside_the_path_at_their_height():
    """Kerbs line both sides of the path, never on it; seen from the robot, some pixels of the view below the
    horizon end on their tops, at the kerb height, and the rest on the floor."""
    spec = SynthSpec(path=PathKind.LOOP, duration_s=20.0, seed=3, n_obstacles=0, kerb_height_m=0.03)
    world = build_world(spec)
    kerbs = place_kerbs(world.planar, 0.03)
    assert len(kerbs) > 20
    path = world.planar.points()
    centres = np.array([(x, y) for x, y, *_ in kerbs])
    dist = np.hypot(path[:, None, 0] - centres[None, :, 0], path[:, None, 1] - centres[None, :, 1])  # (path, kerbs)
    gap = dist.min(axis=0)
    assert gap.min() >= KERB_CLEARANCE_M and gap.max() <= KERB_SIDE_M + 1e-6
    # on both sides: the cross product of the heading and the offset takes both signs
    i = dist.argmin(axis=0)
    heading = np.diff(path, axis=0)[np.minimum(i, len(path) - 2)]
    off = centres - path[i]
    side = np.sign(heading[:, 0] * off[:, 1] - heading[:, 1] * off[:, 0])
    assert (side > 0).sum() > 5 and (side < 0).sum() > 5
    cam = world.camera
    r = Renderer(world.scene, cam)
    T_wc = world.T_world_base(5.0) @ cam.T_base_cam
    _img, range_m = r.render(T_wc, 5.0)
    d_world = cam.pixel_bearings() @ T_wc[:3, :3].T
    got = range_m.ravel()
    down = (d_world[:, 2] < -0.05) & np.isfinite(got) & r.valid.ravel()
    z = T_wc[2, 3] + got[down] * d_world[down, 2]
    on_floor, on_kerb = np.abs(z) < 1e-3, np.abs(z - 0.03) < 1e-3
    assert on_kerb.mean() > 0.02 and on_floor.mean() > 0.5


@pytest.mark.parametrize("args,message", [(["--floor-hidden-frames", "-3"], "floor_hidden_frames must be 0 or more"),
                                          (["--duration", "-1"], "duration and fps must be positive"),
                                          (["--kerb-height", "0.5"], "kerb_height_m must lie in [0, camera height"),
                                          (["--floor-contrast", "-1"], "floor_contrast must be 0 or more")])
def test_synth_command_line_bad_values_are_one_line(tmp_path, args, message):
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "windowvo.synth", str(tmp_path / "out"), *args],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("windowvo: error: ") and message in lines[0], p.stderr


def test_texture_wrap_gives_np_mod_bit_for_bit():
    """The atlas's fast wrap (powers of two) is np.mod exactly: edge cases, negatives, +0.0 included."""
    from windowvo.synth.scene import MipAtlas, make_texture, wrap_mod

    atlas = MipAtlas(make_texture(0))
    assert atlas.inv_sizes is not None  # the default texture's levels are powers of two
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-5000, 5000, 20000), rng.normal(0, 1e-6, 2000),
                        [0.0, -0.0, -1024.0, 1024.0, -2048.0, -1e-30, 1e-30, -64.0, 63.99999, -0.5]]).astype(np.float32)
    lv = rng.integers(0, len(atlas.sizes), x.size)
    size, inv_size = atlas.sizes[lv], atlas.inv_sizes[lv]
    fast = wrap_mod(x, size, inv_size)
    ref = np.mod(x, size)
    assert fast.dtype == ref.dtype and np.array_equal(fast.view(np.uint32), ref.view(np.uint32))
