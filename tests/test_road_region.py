"""``backend.ground.road_region``: a keyframe step's length from the floor's pixels (backend/road_region.py).

The floor images here are ray-cast (each pixel's ray meets the floor z = 0, the floor's texture is read there),
not warped by the homography the measurement searches, so the tests check the measurement against the geometry,
not against its own model."""

from __future__ import annotations

import math

import cv2
import gtsam
import numpy as np
import pytest

from windowvo.backend.road_region import (
    MIN_PITCH_SEARCHES,
    RoadRegionCue,
    _Warp,
    base_distance,
    floor_in_camera,
    gradient_along_flow,
    measure_step,
    pixel_grid,
    pooled_pitch,
    range_factor,
    region_rays,
    smoothed,
)
from windowvo.camera import CameraModel
from windowvo.config import BackendConfig, RegionInterpolation, RoadRegionConfig, RobustKind, config_from_dict
from windowvo.errors import ConfigError
from windowvo.geometry import make_T, rot_x, rot_y, rot_z
from windowvo.types import DistortionModel

HEIGHT = 0.5  # the camera above the floor (m)
TEXTURE_M = 0.01  # one texel of the floor's texture (m)


def _camera() -> CameraModel:
    # Camera axes (x right, y down, z forward) in the base (x forward, y left, z up), pitched 12 deg down.
    R_base_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ rot_x(np.radians(-12.0))
    return CameraModel(320, 240, 260.0, 260.0, 160.0, 120.0, DistortionModel.NONE, (),
                       make_T(rot_y(0.0) @ R_base_cam, [0.1, 0.0, HEIGHT]))


def _texture(seed: int, lane_lines: bool) -> np.ndarray:
    """A floor texture of 20 x 20 m: smooth noise at several scales, and lane lines along x when asked."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((2000, 2000), np.float32)
    for cells in (25, 100, 400):
        tex += cv2.resize(rng.normal(0, 1, (cells, cells)).astype(np.float32), (2000, 2000),
                          interpolation=cv2.INTER_CUBIC)
    tex = 110 + 25 * tex / tex.std()
    if lane_lines:
        for y_m in (-0.4, 0.4):  # two bright lines 5 cm wide along x, 0.4 m each side of the path
            r = int((y_m + 10) / TEXTURE_M)
            tex[r - 2:r + 3, :] += 90
    return np.clip(tex, 0, 255)


def _render(camera: CameraModel, T_world_base: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """The floor z = 0 seen by the camera: each pixel's ray meets it, the texture is read there (bilinear)."""
    T_wc = T_world_base @ camera.T_base_cam
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1).astype(float)) @ T_wc[:3, :3].T
    c = T_wc[:3, 3]
    lam = np.where(rays[:, 2] < -1e-6, -c[2] / np.minimum(rays[:, 2], -1e-6), np.nan)
    X = c[None, :] + lam[:, None] * rays
    mx = ((X[:, 0] + 10) / TEXTURE_M).reshape(camera.height, camera.width).astype(np.float32)
    my = ((X[:, 1] + 10) / TEXTURE_M).reshape(camera.height, camera.width).astype(np.float32)
    img = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderValue=0.0)
    img[np.isnan(mx)] = 200.0  # the sky above the horizon
    return np.clip(img, 0, 255).astype(np.uint8)


def _step(yaw: float = 0.03, forward: float = 0.25, sideways: float = 0.01):
    T0 = make_T(rot_z(0.2), [0.3, -0.2, 0.0])
    T1 = T0 @ make_T(rot_z(yaw), [forward, sideways, 0.0])
    return T0, T1


def _measure(camera, T0, T1, texture, est1: np.ndarray | None = None, cfg: RoadRegionConfig | None = None):
    """The step T0 -> T1 measured from the rendered images, the estimate's second pose ``est1`` (default the true one)."""
    cfg = cfg or RoadRegionConfig(enabled=True)
    img0, img1 = smoothed(_render(camera, T0, texture)), smoothed(_render(camera, T1, texture))
    n_cam, h = floor_in_camera(camera.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    E1 = T1 if est1 is None else est1
    return measure_step(camera, img0, img1, T0 @ camera.T_base_cam, E1 @ camera.T_base_cam, n_cam, h, cfg)


def _camera_distance(camera, T0, T1) -> float:
    return float(np.linalg.norm((T1 @ camera.T_base_cam)[:3, 3] - (T0 @ camera.T_base_cam)[:3, 3]))


def test_the_floor_plane_in_the_camera_frame_is_the_camera_height_below_it():
    cam = _camera()
    n, h = floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    assert h == pytest.approx(HEIGHT)
    # The camera looks 12 deg down: the floor's normal (pointing down) is in its y-z plane, mostly +y.
    assert n == pytest.approx([0.0, np.cos(np.radians(12.0)), np.sin(np.radians(12.0))], abs=1e-9)


@pytest.mark.parametrize("start", [0.8, 1.25])
def test_the_step_length_is_measured_from_an_estimate_off_by_a_fifth(start):
    """The estimate's step 20% short or 25% long, its rotation and direction right: the floor's pixels give the
    length to within 1%."""
    cam, tex = _camera(), _texture(1, lane_lines=False)
    T0, T1 = _step()
    d = _camera_distance(cam, T0, T1)
    T_est = T1.copy()
    T_est[:3, 3] = T0[:3, 3] + start * (T1[:3, 3] - T0[:3, 3])  # the base's step scaled; the camera's nearly so
    got = _measure(cam, T0, T1, tex, T_est)
    assert got is not None
    assert abs(got.camera_m / d - 1.0) < 0.01, (got, d)
    assert got.correlation > 0.9 and got.n_pixels >= 300
    assert abs(got.pitch_deg) < 0.3, got  # the floor is where the set-up says


@pytest.mark.parametrize("pitch_search_deg", [0.0, 2.0])
@pytest.mark.parametrize("start", [0.45, 2.2])
def test_a_step_far_off_the_estimate_is_measured_once_the_search_moves_out(start, pitch_search_deg):
    """``monocular_search_shifts``: the estimate's step 0.45x or 2.2x the true one (a monocular run's scale drifted)
    lies beyond the coarse search's +-42%: not measured without the moved grid, within 0.5% with it."""
    cam, tex = _camera(), _texture(1, lane_lines=False)
    T0, T1 = _step()
    d = _camera_distance(cam, T0, T1)
    T_est = T1.copy()
    T_est[:3, 3] = T0[:3, 3] + start * (T1[:3, 3] - T0[:3, 3])
    fixed, moved = (_measure(cam, T0, T1, tex, T_est, RoadRegionConfig(
        enabled=True, pitch_search_deg=pitch_search_deg, monocular_search_shifts=shifts)) for shifts in (0, 2))
    assert fixed is None
    assert moved is not None and abs(moved.camera_m / d - 1.0) < 0.005, (moved, d)


def test_with_wheels_the_search_is_not_moved_out():
    """The calibrated wheels bound the estimate's step: a step 2.2x off it is a slipping wheel, not measured."""
    from windowvo.backend.road_region import RoadRegion

    cam, tex = _camera(), _texture(1, lane_lines=False)
    T0, T1 = _step()
    T_est = T1.copy()
    T_est[:3, 3] = T0[:3, 3] + 2.2 * (T1[:3, 3] - T0[:3, 3])
    cfg = BackendConfig(ground={"road_region": {"enabled": True, "monocular_search_shifts": 2, "pitch_window": 1}})
    img0, img1 = _render(cam, T0, tex), _render(cam, T1, tex)
    for with_wheels in (False, True):
        road = RoadRegion(cam, cfg, _Floor(), {4: T0, 5: T_est}, with_wheels=with_wheels)
        road.after_update(4, img0)
        road.after_update(5, img1)
        assert math.isnan(road.ratio) == with_wheels, with_wheels
        if not with_wheels:
            assert road.ratio == pytest.approx(1 / 2.2, rel=0.01)


def test_a_sideways_error_of_the_direction_is_searched_out():
    """The estimate's direction 1.2 deg off sideways over a floor with lane lines along the path: measured with
    the estimate's direction the length comes out short (2.3% when written); with the direction searched (the
    default) within 0.5% (0.03%)."""
    cam, tex = _camera(), _texture(2, lane_lines=True)
    T0, T1 = _step(yaw=0.0, sideways=0.0)
    d = _camera_distance(cam, T0, T1)
    T_est = T0 @ make_T(np.eye(3), rot_z(np.radians(1.2)) @ (np.linalg.inv(T0) @ T1)[:3, 3])
    # The floor's pitch fixed in both (searched, it takes up part of the direction's error: 1.2% short with the
    # direction fixed), so that the direction's search is what is measured.
    fixed = _measure(cam, T0, T1, tex, T_est, RoadRegionConfig(enabled=True, search_direction_deg=0.0,
                                                                pitch_search_deg=0.0))
    searched = _measure(cam, T0, T1, tex, T_est, RoadRegionConfig(enabled=True, pitch_search_deg=0.0))
    both = _measure(cam, T0, T1, tex, T_est)  # the defaults: direction and pitch searched
    assert fixed is not None and searched is not None and both is not None
    assert abs(fixed.camera_m / d - 1.0) > 0.02, fixed
    assert abs(searched.camera_m / d - 1.0) < 0.005, searched
    assert abs(both.camera_m / d - 1.0) < 0.005, both


@pytest.mark.parametrize("pitch_deg", [-1.0, 1.0])
def test_a_floor_pitched_against_the_set_up_is_searched_out(pitch_deg):
    """The set-up's camera pitched 1 deg off the true one (the images are the true camera's): on the assumed floor
    the length comes out off by several per cent; with the floor's pitch searched (the default) within 1%, and the
    pitch found is the error's."""
    cam, tex = _camera(), _texture(6, lane_lines=False)
    T0, T1 = _step()
    d = _camera_distance(cam, T0, T1)
    img0, img1 = smoothed(_render(cam, T0, tex)), smoothed(_render(cam, T1, tex))
    T_bc_wrong = cam.T_base_cam.copy()
    T_bc_wrong[:3, :3] = T_bc_wrong[:3, :3] @ rot_x(np.radians(pitch_deg))  # about the camera's x axis
    n_cam, h = floor_in_camera(T_bc_wrong, np.array([0.0, 0.0, 1.0]), 0.0)
    args = (cam, img0, img1, T0 @ cam.T_base_cam, T1 @ cam.T_base_cam, n_cam, h)
    assumed = measure_step(*args, RoadRegionConfig(enabled=True, pitch_search_deg=0.0))
    searched = measure_step(*args, RoadRegionConfig(enabled=True))
    assert assumed is not None and searched is not None
    assert abs(assumed.camera_m / d - 1.0) > 0.03, assumed
    assert abs(searched.camera_m / d - 1.0) < 0.01, searched
    assert abs(abs(searched.pitch_deg) - 1.0) < 0.3, searched


def test_a_pixels_gradient_along_its_flow_is_its_share_of_the_gradient():
    """Hand-worked: on a ramp along x (gradient (2, 0) by central differences) a flow along x keeps all of it, one
    along y none, one at 60 deg half; a flat pixel counts as aligned (it has nothing to mislead with)."""
    ramp = np.tile(np.arange(8, dtype=np.float32), (6, 1))  # I(u, v) = u
    uv = np.array([[3, 2], [3, 2], [3, 2], [3, 2]])
    flow = np.array([[5.0, 0.0], [0.0, -2.0], [np.cos(np.radians(60)), np.sin(np.radians(60))], [0.0, 0.0]])
    assert gradient_along_flow(ramp, uv, flow) == pytest.approx([1.0, 0.0, 0.5, 1.0])
    flat = np.full((6, 8), 7.0, np.float32)
    assert gradient_along_flow(flat, uv[:1], flow[:1]) == pytest.approx([1.0])
    # at the image's border the differences are clamped: one-sided, the same direction
    assert gradient_along_flow(ramp, np.array([[0, 0], [7, 5]]), np.array([[1.0, 0.0], [1.0, 0.0]])) == pytest.approx(
        [1.0, 1.0])


def test_pixels_whose_gradient_lies_across_their_flow_are_left_out():
    """A straight step over a floor with two lane lines along the path: the lines' flanks have their gradient across
    the flow (sideways, the flow running along the lines), so ``min_gradient_alignment`` leaves them out of the
    region and keeps the rest; the length is measured as well as before (to 1%)."""
    cam, tex = _camera(), _texture(4, lane_lines=True)
    T0 = make_T(np.eye(3), [0.3, 0.0, 0.0])  # along x, between the lines
    T1 = T0 @ make_T(np.eye(3), [0.25, 0.0, 0.0])
    d = _camera_distance(cam, T0, T1)
    every = _measure(cam, T0, T1, tex, cfg=RoadRegionConfig(enabled=True, min_gradient_alignment=0.0))
    aligned = _measure(cam, T0, T1, tex, cfg=RoadRegionConfig(enabled=True, min_gradient_alignment=0.3))
    assert every is not None and aligned is not None
    assert abs(every.camera_m / d - 1.0) < 0.01 and abs(aligned.camera_m / d - 1.0) < 0.01, (every, aligned, d)
    assert aligned.n_pixels < 0.95 * every.n_pixels, (aligned.n_pixels, every.n_pixels)
    # without the lines the floor's noise has its gradients every way: most stay (0.89 when written; 1 - 2 asin(0.3)
    # / pi = 0.81 if the directions were even, the floor's perspective squeezes its texture along the flow)
    plain = _texture(4, lane_lines=False)
    every_plain = _measure(cam, T0, T1, plain, cfg=RoadRegionConfig(enabled=True, min_gradient_alignment=0.0))
    aligned_plain = _measure(cam, T0, T1, plain, cfg=RoadRegionConfig(enabled=True, min_gradient_alignment=0.3))
    assert every_plain is not None and aligned_plain is not None
    kept = aligned_plain.n_pixels / every_plain.n_pixels
    assert 0.7 < kept < 0.95, kept
    assert (aligned.n_pixels / every.n_pixels) < kept - 0.05  # 0.80 against 0.89 when written


def test_too_few_aligned_pixels_measure_nothing():
    """Every pixel's gradient across its flow (stripes along the path only): nothing is left to tell the length."""
    cam = _camera()
    stripes = np.tile((110 + 60 * np.sin(np.arange(2000) * 2 * np.pi / 7.0)).astype(np.float32)[:, None], (1, 2000))
    T0 = make_T(np.eye(3), [0.3, 0.0, 0.0])
    T1 = T0 @ make_T(np.eye(3), [0.25, 0.0, 0.0])
    assert _measure(cam, T0, T1, stripes, cfg=RoadRegionConfig(enabled=True, min_gradient_alignment=0.5)) is None


def _reference_correlation(cam: CameraModel, img0, img1, uv0, Xk: np.ndarray, mask1, cubic: bool = False) -> float:
    """Zero-mean normalised cross-correlation of the region's pixels in image k-1 with image k sampled (bilinear, or
    bicubic) at the points ``Xk`` (N, 3, camera k), over the points in front of camera k, inside its image (far
    enough from its edges that the interpolation reads its own pixels only) and off its mask: the plain formula, one
    candidate at a time."""
    front = Xk[:, 2] > 1e-6
    uv = np.full((len(Xk), 2), -1.0)
    uv[front] = cam.project(Xk[front])
    far = 3 if cubic else 2
    ok = front & (uv[:, 0] >= 1) & (uv[:, 0] <= cam.width - far) & (uv[:, 1] >= 1) & (uv[:, 1] <= cam.height - far)
    ok[ok] &= mask1[(uv[ok, 1] + 0.5).astype(int), (uv[ok, 0] + 0.5).astype(int)] != 0
    m = uv[ok].astype(np.float32)[None]
    b = cv2.remap(img1, m[..., 0], m[..., 1], cv2.INTER_CUBIC if cubic else cv2.INTER_LINEAR).ravel().astype(float)
    a = img0[uv0[ok, 1], uv0[ok, 0]].astype(float)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


@pytest.mark.parametrize("distorted,cubic", [(False, False), (True, False), (False, True)])
def test_every_candidate_of_a_grid_of_floors_and_lengths_correlates_as_the_plain_formula_says(distorted, cubic):
    """The search scores its candidates all at once (``_Warp.correlations_at``: P floors x L lengths, by weighted
    sums, each coordinate built on its own); each must be the plain correlation of its own warp, also where part of
    the region leaves image k (the longest step) or lands on its mask, through a distorted lens, and with image k
    sampled bicubic (``road_region.interpolation``)."""
    cam = _camera()
    if distorted:
        cam = CameraModel(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, DistortionModel.RADTAN,
                          (-0.2, 0.05, 0.0, 0.0), cam.T_base_cam)
    tex = _texture(3, lane_lines=True)
    T0, T1 = _step()
    img0, img1 = smoothed(_render(cam, T0, tex)), smoothed(_render(cam, T1, tex))
    mask1 = np.full((cam.height, cam.width), 255, np.uint8)
    mask1[200:, 100:180] = 0  # a bonnet in image k
    T_c1_c0 = np.linalg.inv(T1 @ cam.T_base_cam) @ (T0 @ cam.T_base_cam)
    t = T_c1_c0[:3, 3]
    n_cam, h = floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    cfg = RoadRegionConfig(enabled=True)
    uv0, X0 = region_rays(pixel_grid(cam, cfg.step_px), n_cam, h, cfg)
    warp = _Warp(cam, img0, img1, uv0, X0, T_c1_c0[:3, :3], t / np.linalg.norm(t), n_cam, h, 20, mask1,
                 RegionInterpolation.CUBIC if cubic else RegionInterpolation.LINEAR)
    ns = np.stack([rot_x(np.radians(a)) @ n_cam for a in (-1.5, 0.0, 2.0)])
    RX, tn = warp.on_planes(ns, np.tile(t / np.linalg.norm(t), (3, 1)))
    ss = np.linalg.norm(t) / h * np.array([0.7, 1.0, 1.3, 6.0])
    got = np.reshape(warp.correlations_at(RX, tn, ss), (3, 4))
    want = np.array([[_reference_correlation(cam, img0, img1, uv0, RX[p].astype(float) + s * tn[p].astype(float),
                                             mask1, cubic) for s in ss] for p in range(3)])
    assert got == pytest.approx(want, abs=1e-4)
    assert got[1, 1] > 0.9 and got[1, 1] == got.max()  # the true floor and length correlate best


def test_local_contrast_normalisation_evens_a_bright_marking_with_the_floors_texture():
    """``road_region.normalise_px``: a marking 90 grey levels bright beside a texture of 5 levels, normalised over
    6 px neighbourhoods, stands out of it by no more than twice its amplitude (18x before); off, the image is the
    smoothed one unchanged."""
    rng = np.random.default_rng(4)
    img = np.clip(110 + 5 * cv2.GaussianBlur(rng.normal(0, 1, (120, 160)).astype(np.float32), (0, 0), 1.5)
                  / 0.19, 0, 255).astype(np.uint8)
    img[:, 78:83] = np.clip(img[:, 78:83].astype(int) + 90, 0, 255)
    plain, even = smoothed(img, 0.0), smoothed(img, 0.0, normalise_px=6.0)
    assert np.array_equal(smoothed(img, 1.0, normalise_px=0.0), smoothed(img))

    def amplitude(x: np.ndarray, cols: slice) -> float:
        return float(np.percentile(np.abs(x[10:-10, cols] - np.median(x[10:-10, 10:50])), 95))

    texture, marking = slice(10, 50), slice(78, 83)
    assert amplitude(plain, marking) > 8 * amplitude(plain, texture)
    assert amplitude(even, marking) < 2 * amplitude(even, texture)
    assert abs(float(np.mean(even[10:-10, 10:50]))) < 0.3  # zero mean where the texture is


@pytest.mark.parametrize("normalise_px", [0.0, 6.0])
def test_the_step_and_the_pitch_are_measured_with_bicubic_sampling(normalise_px):
    """``interpolation: cubic`` with the images unsmoothed (``blur_px: 0``), plain or contrast-normalised: the step's
    length within 1% and the floor's pitch within 0.3 deg on ray-cast floors with lane lines (measured: within
    0.81% and 0.15 deg on four textures)."""
    cam = _camera()
    cfg = RoadRegionConfig(enabled=True, blur_px=0.0, interpolation=RegionInterpolation.CUBIC,
                           normalise_px=normalise_px)
    n_cam, h = floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    T0, T1 = _step()
    d = _camera_distance(cam, T0, T1)
    for seed in (0, 3):
        tex = _texture(seed, lane_lines=True)
        img0, img1 = (smoothed(_render(cam, T, tex), 0.0, normalise_px) for T in (T0, T1))
        got = measure_step(cam, img0, img1, T0 @ cam.T_base_cam, T1 @ cam.T_base_cam, n_cam, h, cfg)
        assert got is not None
        assert abs(got.camera_m / d - 1.0) < 0.01, (seed, got)
        assert abs(got.pitch_deg) < 0.3, (seed, got)


def test_the_pooled_pitch_is_the_searches_median_once_it_stands_out_of_their_spread():
    assert pooled_pitch([0.9, 1.0, 1.1, 0.95, 1.05], 3.0) == pytest.approx(1.0)
    assert pooled_pitch([0.4, -0.3, 0.1, -0.2, 0.5, 0.0], 3.0) == 0.0  # within their spread of the set-up's
    assert pooled_pitch([0.9, 1.0, 1.1, 1.0], 3.0) == 0.0  # too few searches yet


def test_the_pooled_pitch_claims_no_better_than_the_searches_shared_error():
    """Searches that agree closely on half a degree (a spread of 0.02 deg, a median's standard error of 0.01) may
    share a bias that their spread does not show: with ``systematic_deg`` 0.2 their median must stand 3 x 0.2 deg
    from the set-up's; a degree does."""
    half = [0.48, 0.5, 0.52, 0.49, 0.51, 0.5, 0.5]
    assert pooled_pitch(half, 3.0) == pytest.approx(0.5)
    assert pooled_pitch(half, 3.0, 0.2) == 0.0
    assert pooled_pitch([p + 0.5 for p in half], 3.0, 0.2) == pytest.approx(1.0)
    assert pooled_pitch([-p - 0.5 for p in half], 3.0, 0.2) == pytest.approx(-1.0)


def test_a_step_on_an_untested_pitch_has_its_sigma_widened_by_what_the_pitch_moves_it():
    """Until the pool holds MIN_PITCH_SEARCHES searches, a step's sigma is widened by the length ``untested_pitch_deg``
    moves it; the widening is the measurement's own sensitivity: the step measured on a floor pitched 0.5 deg either
    way (the images the same) moves by what the sigma says a degree does (4.31% and 4.36% when written; within 10%);
    once the pool can be tested, or with the key at 0, the sigma is ``sigma_fraction``."""
    cam, tex = _camera(), _texture(3, lane_lines=False)
    T0, T1 = _step()
    img0, img1 = smoothed(_render(cam, T0, tex)), smoothed(_render(cam, T1, tex))
    n_cam, h = floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    flat = RoadRegionConfig(enabled=True, pitch_search_deg=0.0)
    lengths = [measure_step(cam, img0, img1, T0 @ cam.T_base_cam, T1 @ cam.T_base_cam, rot_x(np.radians(d)) @ n_cam, h,
                            flat).camera_m for d in (-0.5, 0.5)]
    per_deg = abs(math.log(lengths[1] / lengths[0]))  # the length's share a degree of the floor's pitch moves
    cfg = RoadRegionConfig(enabled=True, untested_pitch_deg=1.0)
    cue = RoadRegionCue(cam, cfg, cam.T_base_cam)
    widened = cue.step_sigma_fraction(n_cam, h)
    assert math.sqrt(widened**2 - cfg.sigma_fraction**2) == pytest.approx(per_deg, rel=0.1), (widened, per_deg)
    cue.pitches.extend([0.1] * MIN_PITCH_SEARCHES)
    assert cue.step_sigma_fraction(n_cam, h) == cfg.sigma_fraction
    off = RoadRegionCue(cam, RoadRegionConfig(enabled=True), cam.T_base_cam)
    assert off.step_sigma_fraction(n_cam, h) == off.cfg.sigma_fraction


def test_the_cue_measures_on_the_pooled_pitch_of_its_searches():
    """The set-up's camera pitched 1 deg off, ten consecutive steps, a pool of six searches, then a search at every
    second step (``pitch_every``): the pitch is searched at every step until the pool is full, then at every second;
    the steps are measured on the set-up's pitch (lengths off) until five searches agree on the pitch, then on
    theirs (within 1%)."""
    cam, tex = _camera(), _texture(7, lane_lines=False)
    T_bc_wrong = cam.T_base_cam.copy()
    T_bc_wrong[:3, :3] = T_bc_wrong[:3, :3] @ rot_x(np.radians(1.0))
    cue = RoadRegionCue(cam, RoadRegionConfig(enabled=True, pitch_window=6, pitch_every=2), T_bc_wrong)
    T = [make_T(rot_z(0.2), [0.3, -0.2, 0.0])]
    for _ in range(10):
        T.append(T[-1] @ make_T(rot_z(0.02), [0.25, 0.01, 0.0]))
    # The estimate's base poses carry the true cameras through the wrong mount (as vision's camera poses would).
    est = [Tk @ cam.T_base_cam @ np.linalg.inv(T_bc_wrong) for Tk in T]
    searches, pooled, errors, pitches = [], [], [], []
    for k, Tk in enumerate(T):
        cue.keep_image(k, _render(cam, Tk, tex))
        if k == 0:
            continue
        step = cue.measure(k, est[k - 1], est[k], np.array([0.0, 0.0, 1.0]), 0.0)
        assert step is not None
        searches.append(cue.n_searches)
        pooled.append(len(cue.pitches))
        errors.append(step.camera_m / _camera_distance(cam, T[k - 1], T[k]) - 1.0)
        pitches.append(step.pitch_deg)
    assert searches == [1, 2, 3, 4, 5, 6, 6, 7, 7, 8]
    assert pooled == [1, 2, 3, 4, 5, 6, 6, 6, 6, 6]
    assert all(p == 0.0 for p in pitches[:4]) and all(abs(e) > 0.03 for e in errors[:4]), (pitches, errors)
    assert all(abs(abs(p) - 1.0) < 0.3 for p in pitches[4:]) and all(abs(e) < 0.01 for e in errors[4:]), (
        pitches, errors)


def test_no_measurement_where_the_floor_does_not_tell_the_length():
    cam, tex = _camera(), _texture(3, lane_lines=False)
    T0, _ = _step()
    # A step too short to move the floor's pixels by min_flow_px.
    assert _measure(cam, T0, T0 @ make_T(np.eye(3), [0.002, 0.0, 0.0]), tex) is None
    # A floor without texture: nothing correlates.
    T0, T1 = _step()
    assert _measure(cam, T0, T1, np.full_like(tex, 120.0)) is None


def test_the_bases_distance_follows_the_cameras_on_a_turn():
    """A camera 0.5 m ahead of the base origin: on a turn their paths differ, and the range factor ties the bases'
    distance that the measured cameras' distance implies."""
    T_base_cam = _camera().T_base_cam.copy()
    T_base_cam[0, 3] = 0.5
    T0, T1 = _step(yaw=0.6, forward=0.3, sideways=0.05)
    T_wc0, T_wc1 = T0 @ T_base_cam, T1 @ T_base_cam
    d_cam = float(np.linalg.norm(T_wc1[:3, 3] - T_wc0[:3, 3]))
    d_base = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    assert abs(d_cam - d_base) > 0.01  # the two differ here
    assert base_distance(T_base_cam, T_wc0, T_wc1, d_cam) == pytest.approx(d_base, rel=1e-9)
    # A longer measured step: the cameras' step scaled, the base's follows (not in proportion: the lever arm).
    T_wc1_long = make_T(T_wc1[:3, :3], T_wc0[:3, 3] + 1.1 * (T_wc1[:3, 3] - T_wc0[:3, 3]))
    T_long = T_wc1_long @ np.linalg.inv(T_base_cam)
    assert base_distance(T_base_cam, T_wc0, T_wc1, 1.1 * d_cam) == pytest.approx(
        float(np.linalg.norm(T_long[:3, 3] - T0[:3, 3])), rel=1e-9)


def test_the_range_factor_is_zero_at_the_measured_length_and_whitened_by_its_sigma():
    f = range_factor(1, 2, 0.5, 0.01, RobustKind.NONE, 3.0)
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(gtsam.Rot3.Yaw(0.4), np.array([1.0, 2.0, 0.0])))
    v.insert(2, gtsam.Pose3(gtsam.Rot3.Yaw(0.1), np.array([1.0, 2.5, 0.0])))
    assert f.error(v) == pytest.approx(0.0, abs=1e-12)
    v.update(2, gtsam.Pose3(gtsam.Rot3.Yaw(0.1), np.array([1.0, 2.52, 0.0])))
    assert f.error(v) == pytest.approx(0.5 * (0.02 / 0.01) ** 2, rel=1e-6)


def test_the_cue_measures_consecutive_keyframes_only():
    cam, tex = _camera(), _texture(4, lane_lines=False)
    T0, T1 = _step()
    cue = RoadRegionCue(cam, RoadRegionConfig(enabled=True), cam.T_base_cam)
    cue.keep_image(3, _render(cam, T0, tex))
    cue.keep_image(5, _render(cam, T1, tex))  # keyframe 4 missing (a reset): no step
    assert cue.measure(5, T0, T1, np.array([0.0, 0.0, 1.0]), 0.0) is None
    cue.keep_image(6, _render(cam, T0, tex))
    cue.keep_image(7, _render(cam, T1, tex))
    step = cue.measure(7, T0, T1, np.array([0.0, 0.0, 1.0]), 0.0)
    assert step is not None
    cue.keep_image(-1, None)  # a window reset forgets the kept images
    assert cue.measure(7, T0, T1, np.array([0.0, 0.0, 1.0]), 0.0) is None
    assert step.camera_m == pytest.approx(_camera_distance(cam, T0, T1), rel=0.01)


def _rocked(T: np.ndarray, roll_deg: float, pitch_deg: float) -> np.ndarray:
    """The base pose ``T`` rocked on its suspension (about its own x and y axes, its origin kept)."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ rot_y(np.radians(pitch_deg)) @ rot_x(np.radians(roll_deg))
    return out


def test_on_a_rocking_base_the_step_is_measured_on_the_windows_level_floor():
    """A base rocking by about a degree between keyframes (the window's poses know each keyframe's attitude; the
    floor is level): measured along the set-up's normal (the base's z axis, which rocks with it) the step comes out
    off by several per cent; along the window's mean normal seen from keyframe k-1 (``RoadRegion.level_floor``,
    ``road_region.level_when_rocking``) within 1%. A level window keeps the set-up's normal (None), and so does the
    key off (the default)."""
    import types

    from windowvo.backend.road_region import RoadRegion

    cam, tex = _camera(), _texture(7, lane_lines=False)
    T0, T1 = _step()
    rock = [(0.6, -0.9), (-0.7, 0.8), (0.5, 1.1), (-0.4, -1.0), (0.8, 0.7), (-0.6, -0.8)]  # (roll, pitch) deg
    level = [make_T(rot_z(0.05 * i), [0.25 * i, 0.0, 0.0]) for i in range(len(rock))]
    k = len(rock) - 1
    level[k - 1], level[k] = T0, T1
    poses = {i: _rocked(T, *rock[i]) for i, T in enumerate(level)}
    on = BackendConfig.model_validate({"ground": {"road_region": {"level_when_rocking": True}}})
    region = RoadRegion(cam, on, types.SimpleNamespace(use_ground=True), poses)
    n_base = region.level_floor(k, 0, np.array([0.0, 0.0, 1.0]))
    assert n_base is not None
    # the world's up seen from keyframe k-1 (the rocks' mean is within 0.2 deg of level)
    assert np.degrees(np.arccos(n_base @ (poses[k - 1][:3, :3].T @ [0.0, 0.0, 1.0]))) < 0.3
    img0, img1 = smoothed(_render(cam, poses[k - 1], tex)), smoothed(_render(cam, poses[k], tex))
    d = _camera_distance(cam, poses[k - 1], poses[k])
    cfg = RoadRegionConfig(enabled=True, pitch_search_deg=0.0)  # the assumed floor alone: what the normal does
    args = (cam, img0, img1, poses[k - 1] @ cam.T_base_cam, poses[k] @ cam.T_base_cam)
    set_up = measure_step(*args, *floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0), cfg)
    levelled = measure_step(*args, *floor_in_camera(cam.T_base_cam, n_base, float(n_base @ cam.T_base_cam[:3, 3])
                                                     - HEIGHT), cfg)
    assert set_up is not None and levelled is not None
    assert abs(set_up.camera_m / d - 1.0) > 0.03, set_up
    assert abs(levelled.camera_m / d - 1.0) < 0.01, levelled
    flat = {i: T for i, T in enumerate(level)}
    assert RoadRegion(cam, on, types.SimpleNamespace(use_ground=True), flat).level_floor(
        k, 0, np.array([0.0, 0.0, 1.0])) is None
    assert RoadRegion(cam, BackendConfig(), types.SimpleNamespace(use_ground=True), poses).level_floor(
        k, 0, np.array([0.0, 0.0, 1.0])) is None  # off by default (docs/scale_suite.md: measured, not kept)


def test_the_region_must_reach_beyond_its_near_edge():
    assert BackendConfig().ground.road_region.enabled is True  # on by default
    with pytest.raises(ConfigError, match="far_heights"):
        config_from_dict({"sequence": "x", "backend": {"ground": {"road_region": {"near_heights": 5.0,
                                                                                  "far_heights": 4.0}}}})
    with pytest.raises(ConfigError, match="pitch_far_heights"):
        config_from_dict({"sequence": "x", "backend": {"ground": {"road_region": {"near_heights": 3.0,
                                                                                  "pitch_far_heights": 2.5}}}})


def test_the_summary_counts_the_steps_the_region_measured():
    from windowvo.runtime.outputs import floor_summary
    from windowvo.types import FrameRecord

    def rec(i: int, key: bool, ratio: float) -> FrameRecord:
        return FrameRecord(frame_index=i, timestamp=0.1 * i, n_tracked=100, n_inliers=90, n_detected=0,
                           parallax_px=1.0, rot_comp_parallax_px=1.0, inlier_ratio=0.9, cheirality_ratio=1.0,
                           spread=0.5, is_keyframe=key, keyframe_reason="", gate="", backend_status="ok",
                           n_landmarks=50, reprojection_rms_px=0.5, frontend_ms=1.0, backend_ms=1.0,
                           road_step_ratio=ratio)

    nan = float("nan")
    records = [rec(0, True, nan), rec(1, False, nan), rec(2, True, 1.02), rec(3, True, nan), rec(4, True, 0.98),
               rec(5, True, 1.01)]
    got = floor_summary(records)
    assert got["road_region_steps"] == 3 and got["road_region_ratio_median"] == pytest.approx(1.01)
    off = floor_summary([rec(0, True, nan), rec(1, True, nan)])
    assert off["road_region_steps"] == 0 and off["road_region_ratio_median"] is None


def test_a_masked_bonnet_in_the_region_is_left_out():
    """The robot's own body in the lower image (it moves with the camera: textured, the same in both images) pulls
    the alignment toward no motion (when written: no peak inside the search, so no measurement); masked (the front
    end's masks reach the back end with the image), the floor's pixels alone give the length (-0.15%)."""
    cam, tex = _camera(), _texture(5, lane_lines=False)
    T0, T1 = _step()
    d = _camera_distance(cam, T0, T1)
    bonnet = np.random.default_rng(0).uniform(0, 255, (90, cam.width)).astype(np.uint8)
    imgs = []
    for T in (T0, T1):
        img = _render(cam, T, tex)
        img[-90:] = bonnet  # the lower 90 rows: the body, fixed in the image
        imgs.append(smoothed(img))
    mask = np.full((cam.height, cam.width), 255, np.uint8)
    mask[-95:] = 0
    n_cam, h = floor_in_camera(cam.T_base_cam, np.array([0.0, 0.0, 1.0]), 0.0)
    # The floor's pitch fixed: the mask's effect alone. (Searched, the 480 pixels above the bonnet, all far rows,
    # leave the pitch loose: 0.3 deg off, the length 2.2% short.)
    cfg = RoadRegionConfig(enabled=True, pitch_search_deg=0.0)
    args = (cam, imgs[0], imgs[1], T0 @ cam.T_base_cam, T1 @ cam.T_base_cam, n_cam, h, cfg)
    plain = measure_step(*args)
    masked = measure_step(*args, masks=(mask, mask))
    assert plain is None or abs(plain.camera_m / d - 1.0) > 0.03, plain
    assert masked is not None and abs(masked.camera_m / d - 1.0) < 0.01, masked


@pytest.mark.slow
def test_a_window_reset_between_measured_steps_keeps_the_run_going(tmp_path, monkeypatch):
    """A degenerate update (a landmark with one projection) at keyframe 15 of a rendered street with the floor's
    region on: the window resets once, the step into the failed keyframe is not measured (its image never reached
    the cue), and the run goes on measuring steps to a metric end."""
    from windowvo.backend import factors as fac
    from windowvo.backend.factors import X
    from windowvo.backend.smoother import SlidingWindowBackend
    from windowvo.runtime.job import run_job
    from windowvo.tools import scale_suite as ss

    submit = SlidingWindowBackend.submit
    injected: list[int] = []

    def degenerate_once(self, graph, values, ts_map, remove):
        if self.k == 15 and not injected:
            injected.append(self.k)
            key = fac.L(10**9)
            values.insert(key, gtsam.Point3(5.0, 1.0, 1.0))
            ts_map.insert((key, float(self.k)))
            graph.add(gtsam.GenericProjectionFactorCal3_S2(np.array([300.0, 120.0]), gtsam.noiseModel.Isotropic.Sigma(
                2, 1.0), X(self.k), key, self.K, self.body_P_sensor))
        return submit(self, graph, values, ts_map, remove)

    monkeypatch.setattr(SlidingWindowBackend, "submit", degenerate_once)
    case = ss.ScaleCase("street_reset", "street", {"path": "straight", "seed": 341, "duration_s": 5.0,
                                                   **ss.STREET_IMAGE,
                                                   "wheel": {"scale_error": 0.02, "yaw_bias_per_m": 0.002}})
    data = ss.case_config(case, tmp_path, tmp_path / "out", "fused", ("backend.ground.road_region.enabled=true",))
    rep = run_job(config_from_dict(data))
    assert injected == [15] and rep.result.n_resets == 1
    ratios = [r.road_step_ratio for r in rep.result.records if r.is_keyframe]
    after = [x for x in ratios[16:] if np.isfinite(x)]
    assert len(after) >= 10, ratios  # measured again after the reset
    assert rep.result.metric and rep.accuracy is not None
    assert rep.accuracy.ate_se3_rmse_m < 0.01 * rep.accuracy.path_length_m


class _Floor:
    """What ``RoadRegion`` reads of the window's floor model: a metric floor at the set-up's height."""

    use_ground = True
    camera_height_m = HEIGHT
    cues = None  # no cue check
    base_rocking_deg = float("nan")  # a level base (no plane fit has judged it)

    def ground_active(self) -> bool:
        return True

    def floor_normal_base(self):
        return None

    def floor_offset(self, n_base) -> float:
        return 0.0

    def ties_allowed(self) -> bool:
        return True


@pytest.mark.parametrize("forward", [0.05, 0.25, 1.2])
@pytest.mark.parametrize("metric_start", [False, True])
def test_a_monocular_runs_first_baseline_is_measured_by_the_region(forward, metric_start):
    """``road_region.metric_start``: keyframe 1's camera at the two views' rotation and direction but a unit baseline
    (1 m: 0.8-20x the true step of 5 cm to 1.2 m, 0.1-2.4 camera heights), keyframe 0's image kept: the region
    measures the camera's first step to within 2% (when written: 1.3% short, 0.1% short, 1.5% short; off: nothing)."""
    from windowvo.backend.road_region import RoadRegion

    cam, tex = _camera(), _texture(8, lane_lines=False)
    T0 = np.eye(4)  # keyframe 0's base is the world
    T1 = make_T(rot_z(0.02), [forward, 0.0, 0.0])
    T_wc1 = T1 @ cam.T_base_cam
    true_m = float(np.linalg.norm(T_wc1[:3, 3] - cam.T_base_cam[:3, 3]))
    unit = T_wc1.copy()
    unit[:3, 3] = cam.T_base_cam[:3, 3] + (T_wc1[:3, 3] - cam.T_base_cam[:3, 3]) / true_m
    cfg = BackendConfig(ground={"road_region": {"enabled": True, "metric_start": metric_start}})
    road = RoadRegion(cam, cfg, _Floor(), {0: T0})
    road.after_update(0, _render(cam, T0, tex))  # keeps keyframe 0's image, measures nothing
    got = road.first_baseline(_render(cam, T1, tex), None, unit)
    if not metric_start:
        assert got is None
        return
    assert got is not None and got == pytest.approx(true_m, rel=0.02), (got, true_m)


@pytest.mark.parametrize("most", [None, 40])
def test_the_region_measures_only_where_the_corners_on_the_floor_are_few(most):
    """``max_floor_landmarks``: with 40 floor landmarks tied in the window the step is not measured, with 39 it is
    (null: always)."""
    from windowvo.backend.road_region import RoadRegion

    cam, tex = _camera(), _texture(6, lane_lines=False)
    T0, T1 = _step()
    cfg = BackendConfig(ground={"road_region": {"enabled": True, "max_floor_landmarks": most}})
    road = RoadRegion(cam, cfg, _Floor(), {4: T0, 5: T1})
    img0, img1 = _render(cam, T0, tex), _render(cam, T1, tex)
    for n_tied, measured in ((40, most is None), (39, True)):
        road.forget()
        road.after_update(4, img0, None, n_tied)
        height = road.after_update(5, img1, None, n_tied)
        assert (height is not None) == measured, (n_tied, most)
        if measured:
            assert height == pytest.approx(HEIGHT, rel=0.01)  # the true step: the known height


def test_steps_on_an_untested_pitch_are_measured_again_once_it_is_tested():
    """With wheels (without, each step is tied as measured): the set-up's camera pitched 1 deg off its real mount,
    eight steps (``RoadRegion``, the defaults: the pitch searched and pooled). The first MIN_PITCH_SEARCHES - 1 steps,
    measured on the set-up's pitch, are 3-10% off: each is recorded (``ratio``) but neither tied (nothing pending) nor
    handed to the cue check (no height). At the step whose search completes the pool, they are measured again on the
    pooled pitch (without a search of their own) and join it: every pending step then lies within 1% of the true
    length, and the cue check gets their lengths (``revised``). From then on each step is pending alone."""
    from dataclasses import replace as dc_replace

    from windowvo.backend.road_region import MIN_PITCH_SEARCHES, RoadRegion

    cam, tex = _camera(), _texture(7, lane_lines=False)
    T_bc_wrong = cam.T_base_cam.copy()
    T_bc_wrong[:3, :3] = T_bc_wrong[:3, :3] @ rot_x(np.radians(1.0))
    T = [make_T(rot_z(0.2), [0.3, -0.2, 0.0])]
    for _ in range(8):
        T.append(T[-1] @ make_T(rot_z(0.02), [0.25, 0.01, 0.0]))
    # The estimate's base poses carry the true cameras through the wrong mount (as vision's camera poses would).
    est = {k: Tk @ cam.T_base_cam @ np.linalg.inv(T_bc_wrong) for k, Tk in enumerate(T)}
    cfg = BackendConfig(ground={"road_region": {"enabled": True}})
    road = RoadRegion(dc_replace(cam, T_base_cam=T_bc_wrong), cfg, _Floor(), est, with_wheels=True)
    alone = RoadRegion(dc_replace(cam, T_base_cam=T_bc_wrong), cfg, _Floor(), est)  # no wheels: tied as measured
    for k, Tk in enumerate(T):
        image = _render(cam, Tk, tex)
        height = road.after_update(k, image, None)
        alone.after_update(k, image, None)
        if k == 0:
            continue
        assert [s.keyframe for s in alone.pending] == [k] and alone.ratio == road.ratio
        assert np.isfinite(road.ratio)  # measured every time
        assert road.cue is not None and road.cue.n_searches == k  # one search a step: none to measure again
        if k < MIN_PITCH_SEARCHES:
            assert height is None and road.pending == [] and road.revised == {}, k
            assert abs(road.ratio - 1.0) > 0.03, (k, road.ratio)  # the estimate's cameras are the true ones
            continue
        want = list(range(1, k + 1)) if k == MIN_PITCH_SEARCHES else [k]
        assert [s.keyframe for s in road.pending] == want, k
        for s in road.pending:
            assert s.camera_m / _camera_distance(cam, T[s.keyframe - 1], T[s.keyframe]) == pytest.approx(1.0, abs=0.01)
        assert height == pytest.approx(HEIGHT, rel=0.01)
        assert sorted(road.revised) == want[:-1]
        for j, length in road.revised.items():  # the base's step in the estimate's frame, measured
            assert length == pytest.approx(float(np.linalg.norm(est[j][:3, 3] - est[j - 1][:3, 3])), rel=0.01), j
    # The pending steps become range factors, only those whose first pose lies after the window's first keyframe.
    from windowvo.backend.factors import X as pose_key
    from windowvo.backend.road_region import RoadStep

    road.pending = [RoadStep(j, 0.25, 0.25, 0.25, 0.9, 500, 0.0, 0.03) for j in (3, 4, 5)]
    graph = gtsam.NonlinearFactorGraph()
    road.add_factor(graph, w0=3)
    assert [graph.at(i).keys() for i in range(graph.size())] == [[pose_key(4), pose_key(5)]]
    assert road.pending == [] and road.n_factors == 1


def _tilted(cam: CameraModel, T_world_base: np.ndarray, deg: float) -> np.ndarray:
    """The base pose whose camera is turned by ``deg`` about its own x axis, its centre kept."""
    T_wc = T_world_base @ cam.T_base_cam
    T_wc[:3, :3] = T_wc[:3, :3] @ rot_x(np.radians(deg))
    return T_wc @ np.linalg.inv(cam.T_base_cam)


@pytest.mark.parametrize("deg", [0.15, -0.15])
def test_on_a_rocking_base_a_step_is_tied_along_its_ridge_with_the_cameras_tilt(deg):
    """The estimate's newer camera tilted 0.15 deg off when the step is measured: its length comes out 2-3% off (a
    tilted camera moves the floor's pixels as a longer step does). On a level base the range factor keeps that
    length at the true poses; on a rocking base, with ``tilt_ridge_deg``, the step goes in along its ridge with the
    tilt, so at the true poses (their tilt, not the measuring estimate's) its residual is within 0.3% (0.02-0.07%
    when written)."""
    import gtsam

    from windowvo.backend.factors import X
    from windowvo.backend.road_region import RoadRegion

    cam, tex = _camera(), _texture(3, lane_lines=False)
    T0, T1 = _step()
    img0, img1 = _render(cam, T0, tex), _render(cam, T1, tex)
    truth = gtsam.Values()
    truth.insert(X(4), gtsam.Pose3(T0))
    truth.insert(X(5), gtsam.Pose3(T1))
    errors = {}
    for rocking in (False, True):
        floor = _Floor()
        floor.base_rocking_deg = 1.0 if rocking else float("nan")
        cfg = BackendConfig(ground={"road_region": {"enabled": True, "pitch_window": 1, "pitch_search_deg": 0.0,
                                                    "tilt_ridge_deg": 0.1}})
        road = RoadRegion(cam, cfg, floor, {4: T0, 5: _tilted(cam, T1, deg)})
        road.after_update(4, img0)
        assert road.after_update(5, img1) is not None
        step = road.pending[0]
        assert abs(step.camera_m / _camera_distance(cam, T0, T1) - 1.0) > 0.02, step  # measured at the wrong tilt
        assert (step.tilt_slope != 0.0) == rocking
        graph = gtsam.NonlinearFactorGraph()
        road.add_factor(graph, w0=0)
        f = graph.at(0)
        e = float(np.asarray(f.unwhitenedError(truth)).ravel()[0])
        errors[rocking] = abs(e) if rocking else abs(e) / step.base_m  # the ridge's is in log units already
    assert errors[False] > 0.02, errors
    assert errors[True] < 0.003, errors


def test_the_ridge_factors_jacobians_are_its_errors_derivatives():
    """``_ridge_error``'s analytic Jacobians against central differences, at poses whose step and tilt are both off
    the measured ones."""
    import gtsam

    from windowvo.backend.factors import X
    from windowvo.backend.road_region import RoadStep, ridge_factor
    from windowvo.config import RobustKind

    cam = _camera()
    T0, T1 = _step()
    R_measured = (np.linalg.inv(T0 @ cam.T_base_cam) @ (T1 @ cam.T_base_cam))[:3, :3]
    step = RoadStep(5, 0.27, 0.27, 0.26, 0.9, 500, 0.0, 0.03, 20.0, R_measured)
    f = ridge_factor(X(4), X(5), step, cam.T_base_cam, RobustKind.NONE, 1.0)
    values = gtsam.Values()
    values.insert(X(4), gtsam.Pose3(T0))
    values.insert(X(5), gtsam.Pose3(T1 @ make_T(rot_x(0.02) @ rot_y(0.04), [0.01, 0.02, 0.03])))
    jac = f.linearize(values).jacobian()[0]  # whitened: sigma 0.03 (log units)
    eps = 1e-6
    for j, key in enumerate((X(4), X(5))):
        for i in range(6):
            d = np.zeros(6)
            d[i] = eps
            out = []
            for sgn in (1.0, -1.0):
                v = gtsam.Values(values)
                v.update(key, values.atPose3(key).retract(sgn * d))
                out.append(float(np.asarray(f.unwhitenedError(v)).ravel()[0]))
            numeric = (out[0] - out[1]) / (2 * eps) / 0.03
            assert jac[0, 6 * j + i] == pytest.approx(numeric, abs=1e-4), (key, i)
