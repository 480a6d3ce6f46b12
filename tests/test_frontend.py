"""Front end on rendered frames, checked against the renderer's ground truth."""

import cv2
import numpy as np
import pytest

from windowvo.camera import CameraModel
from windowvo.config import DetectionOrder, FrontendConfig, GateConfig, KeyframeConfig
from windowvo.frontend.frontend import Frontend
from windowvo.frontend.tracker import (
    KLTTracker,
    ORBTracker,
    cell_counts,
    grid_cells,
    grid_select,
    resolve_detection_order,
)
from windowvo.frontend.two_view import two_view_geometry
from windowvo.geometry import inv_T, rotation_angle
from windowvo.synth.generate import LensPreset, SynthSpec, build_world, lens_fields
from windowvo.synth.paths import PathKind
from windowvo.synth.scene import Renderer
from windowvo.types import Frame, GateOutcome, KeyframeReason


@pytest.fixture(scope="module")
def world():
    w = build_world(SynthSpec(path=PathKind.LOOP, duration_s=12.0, seed=11))
    return w, Renderer(w.scene, w.camera)


def render(world, t):
    w, r = world
    T_wc = w.T_world_base(t) @ w.camera.T_base_cam
    img, _ = r.render(T_wc, t)
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8), T_wc


def project(cam, T_wc, p):
    T = inv_T(T_wc)
    pc = p @ T[:3, :3].T + T[:3, 3]
    return cam.project(pc), pc[:, 2]


@pytest.mark.parametrize("tracker_cls", [KLTTracker])
def test_tracks_follow_ground_truth_after_10_frames(world, tracker_cls):
    w, r = world
    cam = w.camera
    tr = tracker_cls(FrontendConfig())
    img0, T0 = render(world, 3.0)
    first = tr.track(img0)
    p_world = r.surface_points(T0, first.pixels.astype(float), 3.0)
    ids0 = first.ids
    for i in range(1, 11):
        img, T = render(world, 3.0 + i / 20.0)
        ts = tr.track(img)
    common, a, b = np.intersect1d(ids0, ts.ids, return_indices=True)
    assert len(common) > 100
    uv_gt, _z = project(cam, T, p_world[a])
    # drop points that became occluded (the ray-cast from the new pose hits something else)
    p_check = r.surface_points(T, uv_gt, 3.5)
    visible = np.linalg.norm(p_check - p_world[a], axis=1) < 0.05
    err = np.linalg.norm(ts.pixels[b][visible] - uv_gt[visible], axis=1)
    assert np.median(err) < 0.3, np.median(err)
    assert np.mean(err < 2.0) > 0.9


def test_ransac_survivors_are_almost_all_correct(world):
    """Every keyframe-to-keyframe correspondence that survives RANSAC is checked with ground truth."""
    w, r = world
    cam = w.camera
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(), GateConfig())
    wrong = total = 0
    prev = None  # (track id -> surface point) at the previous keyframe
    for i in range(80):
        t = 1.0 + i / 20.0
        img, T = render(world, t)
        fo = fe.process(Frame(i, t, img))
        if not fo.is_keyframe:
            continue
        if prev is not None:
            sel = [j for j, tid in enumerate(fo.track_ids) if int(tid) in prev]
            P = np.stack([prev[int(fo.track_ids[j])] for j in sel])
            ok = np.all(np.isfinite(P), axis=1)
            uv, _z = project(cam, T, P[ok])
            err = np.linalg.norm(uv - fo.pixels[sel][ok], axis=1)
            wrong += int((err > 2.0).sum())
            total += int(ok.sum())
        pts = r.surface_points(T, fo.pixels, t)
        prev = {int(tid): p for tid, p in zip(fo.track_ids, pts)}
    assert total > 1000
    assert wrong / total < 0.01, (wrong, total)


def _two_view_errors(cam, ids0, px0, ids1, px1, T0, T1) -> tuple[float, float]:
    """Rotation error and translation-direction error (deg) of the essential-matrix pose between two
    frames' common tracks, against the true camera poses T0, T1 (T_world_cam)."""
    _common, a, b = np.intersect1d(ids0, ids1, return_indices=True)
    res = two_view_geometry(cam.undistort_normalized(px0[a]), cam.undistort_normalized(px1[b]), cam.fx, 0.5, 0.999)
    T_c1_c0 = inv_T(T1) @ T0
    rot_err = np.degrees(rotation_angle(res.R_cur_kf.T @ T_c1_c0[:3, :3]))
    t_gt = T_c1_c0[:3, 3] / np.linalg.norm(T_c1_c0[:3, 3])
    dir_err = np.degrees(np.arccos(np.clip(np.dot(res.t_cur_kf, t_gt), -1, 1)))
    return float(rot_err), float(dir_err)


def test_relative_pose_from_rendered_pair(world):
    w, _r = world
    cam = w.camera
    tr = KLTTracker(FrontendConfig(max_features=300))
    img0, T0 = render(world, 2.0)
    s0 = tr.track(img0)
    for i in range(1, 16):
        img, T1 = render(world, 2.0 + i / 20.0)
        s1 = tr.track(img)
    rot_err, dir_err = _two_view_errors(cam, s0.ids, s0.pixels, s1.ids, s1.pixels, T0, T1)
    assert rot_err < 0.1, rot_err
    assert dir_err < 1.0, dir_err


def test_no_keyframes_while_standing_still(world):
    cam = world[0].camera
    img, _ = render(world, 4.0)
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(max_interval_s=0.5), GateConfig())
    rng = np.random.default_rng(0)
    kfs = 0
    for i in range(60):  # 3 s standing still, with sensor noise
        noisy = np.clip(img.astype(np.int16) + rng.integers(-2, 3, img.shape), 0, 255).astype(np.uint8)
        fo = fe.process(Frame(i, i / 20.0, noisy), odom_motion=(0.0, 0.0))
        kfs += fo.is_keyframe
    assert kfs == 1  # only the first frame


def test_pure_rotation_is_flagged_low_parallax():
    spec = SynthSpec(path=PathKind.TURN_IN_PLACE, duration_s=12.0, seed=3)
    w = build_world(spec)
    r = Renderer(w.scene, w.camera)
    fe = Frontend(w.camera, FrontendConfig(), KeyframeConfig(), GateConfig())
    gates = []
    for i, t in enumerate(np.arange(4.5, 6.5, 0.05)):  # spinning in place
        T = w.T_world_base(t) @ w.camera.T_base_cam
        img, _ = r.render(T, t)
        fo = fe.process(Frame(i, float(t), np.clip(img * 255, 0, 255).astype(np.uint8)))
        if fo.is_keyframe and i > 0:
            gates.append(fo.gate)
    assert gates, "rotation should still create keyframes (tracks leave the view)"
    # The camera sits 0.25 m ahead of the turning axis, so a long spin does translate it a
    # little; most keyframes of the spin must still be recognised as (near) pure rotation.
    low = sum(g is GateOutcome.LOW_PARALLAX for g in gates)
    assert low >= 0.7 * len(gates), gates
    assert GateOutcome.CHEIRALITY not in gates


def test_orb_tracker_keeps_ids(world):
    tr = ORBTracker(FrontendConfig())
    img0, _ = render(world, 1.0)
    img1, _ = render(world, 1.05)
    a = tr.track(img0)
    b = tr.track(img1)
    assert len(np.intersect1d(a.ids, b.ids)) > 50


def test_masks_keep_features_out(world):
    img, _ = render(world, 2.0)
    static = np.full(img.shape, 255, np.uint8)
    static[300:, :] = 0  # robot body in the lower part of the view
    per_frame = np.full(img.shape, 255, np.uint8)
    per_frame[:, :200] = 0  # a person on the left
    fe = Frontend(world[0].camera, FrontendConfig(), KeyframeConfig(), GateConfig(), static_mask=static)
    for i in range(3):
        img, _ = render(world, 2.0 + i / 20.0)
        fo = fe.process(Frame(i, 2.0 + i / 20.0, img, mask=per_frame))
        assert len(fo.pixels) > 50
        assert np.all(fo.pixels[:, 1] < 300) and np.all(fo.pixels[:, 0] >= 200)


def test_track_history_is_kept_for_live_tracks(world):
    tr = KLTTracker(FrontendConfig())
    for i in range(8):
        img, _ = render(world, 1.0 + i / 20.0)
        ts = tr.track(img)
    oldest = int(ts.ids[np.argmax(ts.ages)])
    hist = tr.history(oldest)
    assert len(hist) == int(ts.ages.max()) + 1
    assert [f for f, _, _ in hist] == list(range(8 - len(hist), 8))
    assert np.allclose(hist[-1][1:], ts.pixels[np.argmax(ts.ages)])
    assert len(tr.history(oldest, last=3)) == 3


# ---------------------------------------------------------------------------- lenses


@pytest.fixture(scope="module")
def fisheye_world():
    w = build_world(SynthSpec(path=PathKind.LOOP, duration_s=12.0, seed=11, **lens_fields(LensPreset.FISHEYE)))
    return w, Renderer(w.scene, w.camera)


def test_fisheye_tracks_follow_ground_truth(fisheye_world):
    """KLT in the distorted fisheye image, checked against the lens projection of the true points."""
    w, r = fisheye_world
    cam = w.camera
    tr = KLTTracker(FrontendConfig())
    img0, T0 = render(fisheye_world, 3.0)
    first = tr.track(img0)
    p_world = r.surface_points(T0, first.pixels.astype(float), 3.0)
    for i in range(1, 11):
        img, T = render(fisheye_world, 3.0 + i / 20.0)
        ts = tr.track(img)
    _common, a, b = np.intersect1d(first.ids, ts.ids, return_indices=True)
    uv_gt, _z = project(cam, T, p_world[a])
    visible = np.linalg.norm(r.surface_points(T, uv_gt, 3.5) - p_world[a], axis=1) < 0.05
    err = np.linalg.norm(ts.pixels[b][visible] - uv_gt[visible], axis=1)
    assert visible.sum() > 80
    # Coarser than the pinhole's (0.3 px): f = 230 px, and the tracks 60-90 deg off-axis lie on the
    # floor right beside the robot, where patches deform fastest (about 1 px after 10 frames).
    assert np.median(err) < 0.6, np.median(err)
    assert np.mean(err < 2.0) > 0.85
    assert np.degrees(cam.ray_angle(ts.pixels[b][visible])).max() > 60.0  # far off-axis tracks too


@pytest.mark.parametrize("bound_deg", [60.0, 75.0])
def test_field_of_view_bound_and_undistorted_pixels(fisheye_world, bound_deg):
    """Only tracks within the bound reach the back end, and their pinhole pixels are where an ideal
    pinhole camera with the same K sees the true point (up to tracking noise times the stretch)."""
    w, r = fisheye_world
    cam = w.camera
    fe = Frontend(cam, FrontendConfig(max_ray_angle_deg=bound_deg), KeyframeConfig(), GateConfig())
    img0, T0 = render(fisheye_world, 3.0)
    fo0 = fe.process(Frame(0, 3.0, img0))
    p_world = dict(zip(fo0.track_ids.tolist(), r.surface_points(T0, fo0.pixels, 3.0)))
    angles = []
    for i in range(1, 11):
        img, T = render(fisheye_world, 3.0 + i / 20.0)
        fo = fe.process(Frame(i, 3.0 + i / 20.0, img))
        angles.append(np.degrees(cam.ray_angle(fo.pixels)))
    angles_all = np.concatenate(angles)
    assert angles_all.max() <= bound_deg + 1e-6
    assert angles_all.max() > bound_deg - 10.0  # the bound, not the lens, limits the tracks
    assert fo.pixel_sigma_scale is not None and fo.pixel_sigma_scale.shape == (len(fo.track_ids),)
    sel = [j for j, tid in enumerate(fo.track_ids.tolist()) if tid in p_world]
    P = np.stack([p_world[int(fo.track_ids[j])] for j in sel])
    T_cw = inv_T(T)
    pc = P @ T_cw[:3, :3].T + T_cw[:3, 3]
    ok = np.isfinite(pc).all(axis=1) & (np.linalg.norm(r.surface_points(T, fo.pixels[sel], 3.5) - P, axis=1) < 0.05)
    ideal = pc[ok, :2] / pc[ok, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    err = np.linalg.norm(fo.pixels_undistorted[sel][ok] - ideal, axis=1)
    scale = fo.pixel_sigma_scale[sel][ok]
    assert ok.sum() > 50
    assert scale.min() >= 1.0 - 1e-9 and scale.max() > 2.0  # the far tracks are stretched
    # in image pixels (error / stretch) the undistorted tracks are as good as KLT itself on this lens
    # (test_fisheye_tracks_follow_ground_truth)
    assert np.median(err / scale) < 0.6, np.median(err / scale)
    assert np.mean(err / scale < 2.0) > 0.85


def test_pinhole_front_end_is_unbounded_and_unstretched(world):
    """A normal lens (86 deg) lies inside the default bound: no mask, every stretch exactly 1."""
    w, _r = world
    fe = Frontend(w.camera, FrontendConfig(), KeyframeConfig(), GateConfig())
    assert fe.static_mask is None
    img, _ = render(world, 2.0)
    fo = fe.process(Frame(0, 2.0, img))
    assert len(fo.track_ids) > 100 and np.all(fo.pixel_sigma_scale == 1.0)


def test_relative_pose_from_fisheye_pair(fisheye_world):
    w, _r = fisheye_world
    cam = w.camera
    fe = Frontend(cam, FrontendConfig(max_features=300), KeyframeConfig(), GateConfig())
    img0, T0 = render(fisheye_world, 2.0)
    f0 = fe.process(Frame(0, 2.0, img0))
    for i in range(1, 16):
        img, T1 = render(fisheye_world, 2.0 + i / 20.0)
        f1 = fe.process(Frame(i, 2.0 + i / 20.0, img))
    rot_err, dir_err = _two_view_errors(cam, f0.track_ids, f0.pixels, f1.track_ids, f1.pixels, T0, T1)
    assert rot_err < 0.1, rot_err
    assert dir_err < 1.0, dir_err


def test_grid_cell_counts_and_spread():
    cam = CameraModel(640, 480, 300.0, 300.0, 320.0, 240.0)
    # 8 x 6 cells of 80 x 80 px: two points in cell (row 0, col 0), one in (5, 7), one on the far border
    px = np.array([[1.0, 1.0], [79.0, 79.0], [639.0, 479.0], [560.0, 400.0], [80.0, 0.0]])
    counts = cell_counts(px, (480, 640), 8, 6)
    assert counts[0, 0] == 2 and counts[5, 7] == 2 and counts[0, 1] == 1 and counts.sum() == 5
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(), GateConfig())
    assert fe.spread(px) == 3 / 48
    assert fe.spread(np.zeros((0, 2))) == 0.0


def test_detection_order_rows_fills_the_top_spread_reaches_the_floor():
    """A budget short of the cells' room: ``rows`` spends it on the upper cells (the road below the horizon
    gets nothing), ``spread`` gives every cell one corner per round, the bottom rows first."""
    # 2 x 3 cells of 100 x 100 px, four candidates per cell, best first within a cell, top row first
    cells = [(r, c) for r in range(3) for c in range(2)]
    cand = np.array([[100 * c + 10 + 20 * i, 100 * r + 50] for r, c in cells for i in range(4)], float)
    rows_sel = grid_select(cand, np.zeros((0, 2)), (300, 200), 2, 3, 8, 4, DetectionOrder.ROWS)
    assert (cand[rows_sel][:, 1] < 100).all()  # all in the top row: the rows below (the road) get none
    spread_sel = grid_select(cand, np.zeros((0, 2)), (300, 200), 2, 3, 8, 4, DetectionOrder.SPREAD)
    # one per cell (the best of each), then a second round from the bottom row up
    assert spread_sel[:6].tolist() == [16, 20, 8, 12, 0, 4]
    assert spread_sel[6:].tolist() == [17, 21]
    # cells already full take nothing, in either order
    full = np.repeat([[150.0, 250.0]], 4, axis=0)
    assert not np.isin(grid_select(cand, full, (300, 200), 2, 3, 30, 4, DetectionOrder.SPREAD), range(20, 24)).any()
    assert resolve_detection_order(DetectionOrder.AUTO, floor_only_scale=True) is DetectionOrder.SPREAD
    assert resolve_detection_order(DetectionOrder.AUTO, floor_only_scale=False) is DetectionOrder.ROWS
    assert resolve_detection_order(DetectionOrder.ROWS, floor_only_scale=True) is DetectionOrder.ROWS


def test_losing_every_track_at_once_makes_a_keyframe(world):
    """Every track lost in one frame (the lens covered for a frame) leaves no parallax to judge a standstill by;
    without wheels the old code took that as standing still and, once the view came back with new tracks only,
    never made another keyframe."""
    cam = world[0].camera
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(), GateConfig())
    assert fe.process(Frame(0, 0.0, render(world, 1.0)[0])).is_keyframe
    covered = np.full((cam.height, cam.width), 90, np.uint8)
    fo = fe.process(Frame(1, 0.05, covered))
    assert len(fo.track_ids) == 0 and not fo.standstill
    assert fo.is_keyframe and fo.keyframe_reason is KeyframeReason.TRACK_LOSS
    later = [fe.process(Frame(i, i * 0.05, render(world, 1.0 + i * 0.05)[0])) for i in range(2, 30)]
    assert sum(f.is_keyframe for f in later[1:]) >= 2  # keyframing goes on from the view that came back


def test_gain_normaliser_cancels_exposure_steps_but_not_scene_changes(world):
    """An exposure step scales the whole image: every frame comes out at the target mean, exactly the plain
    normalisation. A region that changes alone (a bright floor coming into view under a blank one) must not
    change the grey levels elsewhere; scaling every frame to one mean did (by 14% here)."""
    from windowvo.frontend.frontend import GainNormalizer

    img = render(world, 2.0)[0]
    gn = GainNormalizer(110.0)
    first = gn(img)
    assert first.mean() == pytest.approx(110.0, abs=1.0)
    darker = np.clip(img.astype(float) * 0.7, 0, 255).astype(np.uint8)  # auto-exposure step
    out = gn(darker)
    assert np.array_equal(out, cv2.convertScaleAbs(darker, alpha=110.0 / cv2.mean(darker)[0]))
    gn2 = GainNormalizer(110.0)
    blank = img.copy()
    blank[240:] = int(img[235:240].mean())
    before = gn2(blank).astype(float)
    after = gn2(img).astype(float)
    plain = cv2.convertScaleAbs(img, alpha=110.0 / cv2.mean(img)[0]).astype(float)
    assert np.abs(after[:200] - before[:200]).mean() < 1.0  # unchanged top half: the same grey levels
    assert np.abs(plain[:200] - before[:200]).mean() > 3.0  # the plain normalisation shifts it (the test can fail)


def test_tracks_survive_a_region_coming_into_view(world):
    """The front end end to end: the lower half of the view changes at once (a dark obstacle leaves it, the
    rendered floor is seen again); tracks in the upper half must survive it (scaling both frames to one mean
    lost most of them: the test can fail)."""
    cam = world[0].camera
    fe = Frontend(cam, FrontendConfig(), KeyframeConfig(), GateConfig())
    img0 = render(world, 2.0)[0].copy()
    img0[240:] = 20
    fo0 = fe.process(Frame(0, 0.0, img0))
    fo1 = fe.process(Frame(1, 0.05, render(world, 2.05)[0]))
    upper = fo0.pixels[:, 1] < 200  # away from the edge of the dark region, whose corners go with it
    kept = np.isin(fo0.track_ids[upper], fo1.track_ids).mean()
    print(f"tracks kept across the change: {kept:.2f}")
    assert kept >= 0.8


# --- the front end's cuts: the same results for less work (docs/performance.md "Front-end cuts") ---


def _textures(shape, n, seed):
    """Random textured uint8 images (blurred noise of a few scales, like camera frames)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        noise = rng.integers(0, 256, shape, dtype=np.uint8)
        out.append(cv2.GaussianBlur(noise, (0, 0), 1.0 + k % 4) if k % 5 else noise)
    return out


@pytest.mark.parametrize("shape", [(370, 1226), (376, 1241), (101, 333)])
def test_area_cell_means_are_cv2_resize_bit_for_bit(shape, monkeypatch):
    """The gain normaliser's cells: exact means from the integral image, rounded like OpenCV, and OpenCV's own
    float32 sums for the cells near a rounding boundary; the same values as ``cv2.resize`` INTER_AREA on every
    image, the near cells included (the test counts them: it can only pass by chance if none came up)."""
    from windowvo.frontend import frontend as fe_mod

    summed = []
    real = fe_mod.opencv_area_cell
    monkeypatch.setattr(fe_mod, "opencv_area_cell", lambda *a: summed.append(a[2:]) or real(*a))
    for img in _textures(shape, 40, seed=shape[1]):
        for cells in ((8, 6), (7, 5)):
            want = cv2.resize(img, cells, interpolation=cv2.INTER_AREA).astype(np.float64)
            assert np.array_equal(fe_mod.area_cell_means(img, cells), want)
    assert summed, "no cell near a rounding boundary came up"
    assert fe_mod.area_grid(480, 640, 8, 6) is None  # a whole number of pixels per cell: cv2.resize's fast path


def test_opencv_area_sums_are_emulated_exactly():
    """``opencv_area_cell`` is OpenCV's INTER_AREA sum before its rounding: checked against cv2.resize of the
    float32 image (the same float32 arithmetic), every cell, bit for bit."""
    from windowvo.frontend.frontend import area_grid, opencv_area_cell

    for img in _textures((370, 1226), 6, seed=3):
        grid = area_grid(370, 1226, 8, 6)
        assert grid is not None
        want = cv2.resize(img.astype(np.float32), (8, 6), interpolation=cv2.INTER_AREA)
        got = np.array([[opencv_area_cell(img, grid, r, c) for c in range(8)] for r in range(6)], np.float32)
        assert np.array_equal(got, want)


def _greedy_reference(cand, existing, shape, cols, rows, budget, per_cell):
    """The selection rule one candidate at a time (what ``grid_select`` did before it was vectorised)."""
    counts = cell_counts(existing, shape, cols, rows)
    chosen = []
    for k, (cy, cx) in enumerate(zip(*grid_cells(cand, shape, cols, rows), strict=True)):
        if counts[cy, cx] < per_cell and len(chosen) < budget:
            counts[cy, cx] += 1
            chosen.append(k)
    return np.asarray(chosen, np.int64)


def test_grid_fill_in_batches_is_one_pass_over_all():
    from windowvo.frontend.tracker import GridFill

    rng = np.random.default_rng(5)
    shape = (370, 1226)
    for _ in range(30):
        cand = (rng.random((int(rng.integers(0, 400)), 2)) * [1226, 370]).astype(np.float32)
        existing = (rng.random((int(rng.integers(0, 150)), 2)) * [1226, 370]).astype(np.float32)
        budget, per_cell = int(rng.integers(1, 150)), int(rng.integers(1, 9))
        want = _greedy_reference(cand, existing, shape, 8, 6, budget, per_cell)
        assert np.array_equal(grid_select(cand, existing, shape, 8, 6, budget, per_cell), want)
        fill = GridFill(existing, shape, 8, 6, budget, per_cell)
        cuts = np.sort(rng.integers(0, len(cand) + 1, 4))
        got = [lo + fill.take(cand[lo:hi]) for lo, hi in zip([0, *cuts], [*cuts, len(cand)], strict=True)]
        assert np.array_equal(np.concatenate(got), want)
        assert fill.full == (len(want) == budget)


def test_detection_searches_only_short_cells_and_stops_when_the_budget_is_full(world, monkeypatch):
    """Tracks fill every cell but twelve (20 new corners needed): the new corners land only in those, and (rows
    order) detection stops at the cell that fills the budget, with the corners that searching every short cell
    and then selecting gives."""
    img = render(world, 2.0)[0]
    cfg = FrontendConfig(detection_order=DetectionOrder.ROWS, max_features=200)  # 5 a cell, up to 7 new ones
    h, w = img.shape
    xs, ys = np.linspace(0, w, 9), np.linspace(0, h, 7)
    short = {(r, c) for r in range(6) for c in range(8) if (r + 2 * c) % 4 == 1}
    pts = np.array([[xs[c] + (xs[c + 1] - xs[c]) * (0.2 + 0.15 * k), ys[r] + (ys[r + 1] - ys[r]) * 0.5]
                    for r in range(6) for c in range(8) if (r, c) not in short for k in range(5)], np.float32)
    assert len(short) == 12 and len(pts) == 180
    calls = []
    real = cv2.goodFeaturesToTrack
    monkeypatch.setattr(cv2, "goodFeaturesToTrack", lambda *a, **k: calls.append(1) or real(*a, **k))

    def tracker():
        tr = KLTTracker(cfg)
        tr.pts, tr.ids, tr.ages = pts.copy(), np.arange(len(pts)), np.zeros(len(pts), np.int32)
        return tr

    tr = tracker()
    assert tr._detect(img, None) == 20
    cy, cx = grid_cells(tr.pts[len(pts):], (h, w), 8, 6)
    assert set(zip(cy.tolist(), cx.tolist(), strict=True)) <= short  # only where tracks were short
    assert 2 <= len(calls) < len(short)  # 20 corners from the first few short cells (up to 7 each)
    tr = tracker()
    every = np.concatenate(list(tr._cell_candidates(img, tr._detection_mask((h, w), None))))
    calls.clear()
    got = tr._new_corners(img, None, 20)
    assert len(calls) < len(short) and len(got) == 20
    assert np.array_equal(got, every[grid_select(every, pts, (h, w), 8, 6, 20, 7)])


def test_backward_flow_only_for_forward_survivors_keeps_every_result(world):
    """The KLT checks with the backward flow run for the forward survivors only: the same tracks survive, at the
    same pixels, as with both flows over every track (Lucas-Kanade tracks each point on its own)."""
    cfg = FrontendConfig()
    tr = KLTTracker(cfg)
    img0, img1 = render(world, 3.0)[0], render(world, 3.3)[0]  # a long step: some tracks fail
    tr.track(img0)
    p0 = tr.pts.reshape(-1, 1, 2)
    lk = dict(winSize=tr.lk_win, maxLevel=cfg.klt_levels, criteria=tr.lk_crit)
    p1, st, err = cv2.calcOpticalFlowPyrLK(img0, img1, p0, None, **lk)
    p0b, stb, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, p0.copy(), **lk, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2)
    b, (h, w) = cfg.border_px, img1.shape
    want = ((st.ravel() == 1) & (stb.ravel() == 1) & (err.ravel() < cfg.klt_max_residual)
            & (np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) < cfg.forward_backward_px)
            & (p1[:, 0] >= b) & (p1[:, 1] >= b) & (p1[:, 0] < w - b) & (p1[:, 1] < h - b))
    ok, got = tr._flow(img0, img1, None)
    assert 0 < want.sum() < len(want)  # some fail, some survive: the test can tell
    assert np.array_equal(ok, want) and np.array_equal(got[ok], p1[want])


def _sheened_pair(shift_px: float, ramp_change: float, contrast: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """A faint texture seen twice, shifted right by ``shift_px``, the second time under a brightness ramp that
    changed by ``ramp_change`` grey levels per pixel (a polished floor's sheen moves with the view)."""
    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (260, 300)).astype(np.float32), (0, 0), 2.0)
    tex = 100.0 + contrast * tex / tex.std()
    M = np.float32([[1, 0, shift_px], [0, 1, 0]])
    moved = cv2.warpAffine(tex, M, (300, 260), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    yy, xx = np.mgrid[0:260, 0:300].astype(np.float32)
    sheen = ramp_change * (xx + 0.5 * yy)
    return (np.clip(tex, 0, 255).astype(np.uint8), np.clip(moved + sheen, 0, 255).astype(np.uint8))


def _median_flow(box: int, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, int]:
    tr = KLTTracker(FrontendConfig(klt_highpass_px=box))
    tr.track(a)
    ids0, p0 = tr.ids.copy(), tr.pts.copy()
    tr.track(b)
    keep = np.isin(ids0, tr.ids)
    return np.median(tr.pts[np.isin(tr.ids, ids0)] - p0[keep], axis=0), int(keep.sum())


def test_tracking_on_the_highpassed_image_ignores_a_changing_sheen():
    """KLT assumes brightness constancy: on a faint texture, a brightness ramp that changes between two frames
    (0.02 grey levels a pixel) pulls the matches along the texture's gradient and ends some tracks. On the image
    less its local mean (``klt_highpass_px``) a locally linear change cancels: the same flow as without it."""
    clean = _sheened_pair(1.3, 0.0)
    sheen = _sheened_pair(1.3, 0.02)
    bias, kept = {}, {}
    for box in (0, 21):
        flow_clean, n_clean = _median_flow(box, *clean)
        flow_sheen, kept[box] = _median_flow(box, *sheen)
        assert n_clean > 150 and abs(flow_clean[0] - 1.3) < 0.06  # both track the clean pair
        bias[box] = float(np.linalg.norm(flow_sheen - flow_clean))
    assert bias[0] > 0.04, bias  # the plain image is pulled: the test can tell the two apart
    assert bias[21] < 0.01, bias
    assert kept[21] >= kept[0], kept


def test_highpass_box_must_be_wider_than_the_klt_window():
    with pytest.raises(ValueError, match="klt_highpass_px"):
        FrontendConfig(klt_highpass_px=9, klt_window_px=9)
    assert FrontendConfig(klt_highpass_px=0).klt_highpass_px == 0
