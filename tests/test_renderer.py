"""The renderer's geometry: the same floor point looks the same from two poses."""

import numpy as np

from windowvo.geometry import inv_T
from windowvo.synth.generate import SynthSpec, build_world
from windowvo.synth.paths import PathKind
from windowvo.synth.scene import Renderer


def test_floor_points_are_photometrically_consistent():
    world = build_world(SynthSpec(path=PathKind.LOOP, duration_s=10.0, seed=2))
    cam = world.camera
    r = Renderer(world.scene, cam)
    T0 = world.T_world_base(2.0) @ cam.T_base_cam
    T1 = world.T_world_base(2.3) @ cam.T_base_cam
    img0, depth0 = r.render(T0, 2.0)
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
    # the depth buffer agrees with the ray-cast points
    d0 = depth0[uv0[:, 1].round().astype(int), uv0[:, 0].round().astype(int)]
    assert np.all(np.isfinite(d0[on_floor]))


def test_rendering_is_deterministic():
    w = build_world(SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=5.0, seed=4))
    r = Renderer(w.scene, w.camera)
    T = w.T_world_base(1.0) @ w.camera.T_base_cam
    a, _ = r.render(T, 1.0)
    b, _ = Renderer(build_world(SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=5.0, seed=4)).scene, w.camera).render(T, 1.0)
    assert np.array_equal(a, b)
    assert a.std() > 0.05  # textured, not flat
