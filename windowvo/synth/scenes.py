"""The street and the warehouse: scenes built around a path from the renderer's planes and boxes.

The room (``scene.make_room_scene``) is the default. A street is a road laid along the path
(the robot drives in its right lane) with lane markings, kerbs and pavements on both sides,
parked cars and building facades. A warehouse is a large hall with a shiny, faintly textured
floor, rows of shelving racks, pallets and people walking across the path.
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass

import numpy as np

from . import exact
from .paths import PlanarPath
from .scene import MovingBox, Plane, Scene, make_room_scene, oriented_box_planes, textured_rect


class SceneKind(str, enum.Enum):
    ROOM = "room"  # a walled room with boxes (the default)
    STREET = "street"  # a road with lane markings, kerbs, pavements, parked cars and facades
    WAREHOUSE = "warehouse"  # a hall with a shiny floor, shelving racks, pallets and a person walking


@dataclass(frozen=True)
class StreetLayout:
    """Lateral layout of the street, metres from the road's centre line (left positive)."""

    lane_w: float = 3.5  # two lanes, the robot in the right one
    parking_w: float = 2.2  # a parking lane beside each kerb
    pavement_w: float = 3.0
    line_w: float = 0.12  # painted lines
    dash_len: float = 3.0
    dash_period: float = 9.0
    behind_m: float = 20.0  # road laid before the path's start ...
    ahead_m: float = 90.0  # ... and beyond its end (what the camera sees ahead)

    @property
    def kerb_offset(self) -> float:
        return self.lane_w + self.parking_w


STREET = StreetLayout()
ASPHALT_BRIGHTNESS, ASPHALT_CONTRAST = 0.55, 0.3  # dark, low-contrast asphalt
PAINT_BRIGHTNESS, PAINT_CONTRAST = 1.6, 0.15  # bright lane markings
PAINT_LIFT_M = 0.003  # markings lie this far above the asphalt (so they win the depth test)
CAR_SIZE = (4.3, 1.8, 1.45)


@dataclass
class Centreline:
    """The road's centre line: a dense polyline with unit tangents and left normals, by arclength."""

    xy: np.ndarray
    s: np.ndarray

    @classmethod
    def along(cls, planar: PlanarPath, offset_left: float, behind: float, ahead: float) -> Centreline:
        pts = planar.points()
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-6])
        pts = pts[keep]
        seg = np.hypot(*np.diff(pts, axis=0).T)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        grid = np.arange(0.0, s[-1], 0.5)
        dense = np.stack([np.interp(grid, s, pts[:, 0]), np.interp(grid, s, pts[:, 1])], axis=1)
        t0 = _unit(dense[1] - dense[0])
        t1 = _unit(dense[-1] - dense[-2])
        before = dense[0] - np.arange(behind, 0.0, -0.5)[:, None] * t0
        after = dense[-1] + np.arange(0.5, ahead + 0.5, 0.5)[:, None] * t1
        xy = np.concatenate([before, dense, after])
        tang = np.gradient(xy, axis=0)
        tang /= np.linalg.norm(tang, axis=1, keepdims=True)
        xy = xy + offset_left * np.stack([-tang[:, 1], tang[:, 0]], axis=1)
        return cls(xy, np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]))

    def at(self, s: float, offset: float) -> np.ndarray:
        """The point ``offset`` m left of the centre line at arclength ``s``."""
        p = np.array([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])])
        return p + offset * self.normal(s)

    def normal(self, s: float) -> np.ndarray:
        i = int(np.clip(np.searchsorted(self.s, s), 1, len(self.s) - 1))
        t = _unit(self.xy[i] - self.xy[i - 1])
        return np.array([-t[1], t[0]])

    def pieces(self, max_len: float = 50.0, sag_m: float = 0.08) -> list[tuple[float, float]]:
        """Arclength intervals short enough that a chord stays within ``sag_m`` of the curve."""
        heading = np.unwrap(exact.arctan2(*np.diff(self.xy, axis=0).T[::-1]))
        curv = np.abs(np.gradient(heading, self.s[1:]))
        radius = 1.0 / max(float(curv.max()), 1e-6)
        step = float(np.clip(np.sqrt(8.0 * radius * sag_m), 4.0, max_len))
        edges = np.append(np.arange(0.0, self.s[-1], step), self.s[-1])
        return [(float(a), float(b)) for a, b in itertools.pairwise(edges) if b - a > 0.5]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(exact.norm(v), 1e-12)


def _strip(line: Centreline, s0: float, s1: float, d0: float, d1: float, z: float, rng: np.random.Generator,
           brightness: float, contrast: float) -> Plane:
    """A horizontal rectangle from ``d0`` to ``d1`` m left of the centre line over arclengths [s0, s1], facing up;
    lengthened at both ends so that the pieces of a curve overlap instead of leaving gaps."""
    a, b = line.at(s0, 0.5 * (d0 + d1)), line.at(s1, 0.5 * (d0 + d1))
    u = _unit(b - a)
    n = np.array([-u[1], u[0]])
    ext = 0.05 + 0.02 * max(abs(d0), abs(d1))
    origin = np.append(a - ext * u + (d0 - 0.5 * (d0 + d1)) * n, z)
    p = textured_rect(origin, np.append(u, 0.0), np.append(n, 0.0), exact.norm(b - a) + 2 * ext,
                      d1 - d0, rng, brightness, facing=origin + [0.0, 0.0, 100.0])
    p.contrast = contrast
    return p


def _wall(line: Centreline, s0: float, s1: float, d: float, z0: float, height: float, rng: np.random.Generator,
          brightness: float, ext: float = 0.0) -> Plane:
    """A vertical rectangle on the chord ``d`` m left of the centre line, facing the centre line."""
    a, b = line.at(s0, d), line.at(s1, d)
    u = _unit(b - a)
    a = a - ext * u
    mid = line.at(0.5 * (s0 + s1), 0.0)
    return textured_rect(np.append(a, z0), np.append(u, 0.0), [0.0, 0.0, 1.0], exact.norm(b - a) + 2 * ext,
                         height, rng, brightness, facing=np.append(mid, z0 + 0.5 * height))


def _road_planes(line: Centreline, kerb_h: float, rng: np.random.Generator) -> list[Plane]:
    """Asphalt, edge lines, kerb faces and pavement tops, piece by piece along the centre line."""
    L = STREET
    k, w = L.kerb_offset, L.line_w
    out: list[Plane] = []
    for s0, s1 in line.pieces():
        out.append(_strip(line, s0, s1, -k, k, 0.0, rng, ASPHALT_BRIGHTNESS, ASPHALT_CONTRAST))
        for d in (-L.lane_w, L.lane_w):  # solid lines between the lanes and the parking lanes
            out.append(_strip(line, s0, s1, d - w / 2, d + w / 2, PAINT_LIFT_M, rng, PAINT_BRIGHTNESS, PAINT_CONTRAST))
        for side in (-1.0, 1.0):
            if kerb_h > 0:
                out.append(_wall(line, s0, s1, side * k, 0.0, kerb_h, rng, 0.8, ext=0.05 + 0.02 * k))
            d0, d1 = sorted((side * k, side * (k + L.pavement_w)))
            out.append(_strip(line, s0, s1, d0, d1, kerb_h, rng, 0.95, 0.7))
    for s in np.arange(0.5 * L.dash_period, line.s[-1] - L.dash_len, L.dash_period):  # the dashed centre line
        out.append(_strip(line, float(s), float(s) + L.dash_len, -w / 2, w / 2, PAINT_LIFT_M, rng,
                          PAINT_BRIGHTNESS, PAINT_CONTRAST))
    return out


def _facades(line: Centreline, kerb_h: float, rng: np.random.Generator) -> list[Plane]:
    """Building fronts at the back of both pavements: 8-25 m wide, 6-20 m tall, each its own shade."""
    out: list[Plane] = []
    d = STREET.kerb_offset + STREET.pavement_w
    for side in (-1.0, 1.0):
        s = 0.0
        while s < line.s[-1] - 1.0:
            s1 = min(s + float(rng.uniform(8.0, 25.0)), float(line.s[-1]))
            out.append(_wall(line, s, s1, side * d, kerb_h, float(rng.uniform(6.0, 20.0)), rng,
                             float(rng.uniform(0.6, 1.1))))
            s = s1
    return out


def _parked_cars(line: Centreline, n: int, s_range: tuple[float, float], rng: np.random.Generator) -> list[Plane]:
    """``n`` cars in the parking lanes (both sides), nose to tail with at least 1.2 m between them."""
    d = STREET.lane_w + 0.5 * STREET.parking_w
    placed: dict[float, list[float]] = {-1.0: [], 1.0: []}
    out: list[Plane] = []
    for _ in range(20 * n):
        if sum(len(v) for v in placed.values()) >= n:
            break
        side = -1.0 if rng.random() < 0.5 else 1.0
        s = float(rng.uniform(*s_range))
        if any(abs(s - o) < CAR_SIZE[0] + 1.2 for o in placed[side]):
            continue
        placed[side].append(s)
        c = line.at(s, side * d)
        nrm = line.normal(s)
        yaw = math.atan2(-nrm[0], nrm[1])
        out.extend(oriented_box_planes(c, yaw, CAR_SIZE, rng, brightness=float(rng.uniform(0.4, 1.1))))
    return out


def make_street_scene(seed: int, planar: PlanarPath, kerb_h: float, n_cars: int,
                      moving: list[MovingBox]) -> Scene:
    """A street along ``planar`` (the robot in the middle of its right lane) with kerbs ``kerb_h`` m high."""
    rng = np.random.default_rng(seed)
    line = Centreline.along(planar, STREET.lane_w / 2, STREET.behind_m, STREET.ahead_m)
    planes = _road_planes(line, kerb_h, rng)
    planes += _facades(line, kerb_h, rng)
    planes += _parked_cars(line, n_cars, (STREET.behind_m - 10.0, float(line.s[-1]) - 20.0), rng)
    return Scene(planes, moving, None, texture_seed=seed)


# ---------------------------------------------------------------------------- warehouse

RACK_DEPTH_M, RACK_UNIT_M, RACK_HEIGHT_M, AISLE_M = 2.2, 2.7, 5.0, 3.0  # back-to-back racks, 3 m aisles
RACK_CLEARANCE_M, PALLET_CLEARANCE_M = 1.2, 0.8  # from the path to a rack / a pallet
WAREHOUSE_FLOOR_GLOSS = 0.2
WAREHOUSE_WALL_M = 8.0


def _rect_distance(pts: np.ndarray, cx: float, cy: float, sx: float, sy: float) -> float:
    dx = np.maximum(np.abs(pts[:, 0] - cx) - sx / 2, 0.0)
    dy = np.maximum(np.abs(pts[:, 1] - cy) - sy / 2, 0.0)
    return float(np.hypot(dx, dy).min())


def place_racks(planar: PlanarPath, half_x: float, half_y: float) -> list[tuple[float, float, float, float, float]]:
    """Rack rows along x, ``(x, y, sx, sy, sz)``: runs of units that keep their clearance from the path."""
    pts = planar.points()[::10]
    out = []
    for y in np.arange(-half_y + 2.0 + RACK_DEPTH_M / 2, half_y - 2.0, RACK_DEPTH_M + AISLE_M):
        run: list[float] = []
        xs = np.arange(-half_x + 2.0 + RACK_UNIT_M / 2, half_x - 2.0 - RACK_UNIT_M / 2, RACK_UNIT_M + 0.05)
        for i, x in enumerate(xs):
            ok = _rect_distance(pts, x, y, RACK_UNIT_M, RACK_DEPTH_M) >= RACK_CLEARANCE_M and i % 6 != 5  # cross aisles
            if ok:
                run.append(float(x))
            if run and (not ok or i == len(xs) - 1 or len(run) == 5):
                x0, x1 = run[0] - RACK_UNIT_M / 2, run[-1] + RACK_UNIT_M / 2
                out.append((0.5 * (x0 + x1), float(y), x1 - x0, RACK_DEPTH_M, RACK_HEIGHT_M))
                run = []
    return out


def place_pallets(rng: np.random.Generator, planar: PlanarPath, n: int, half: float,
                  racks: list[tuple[float, float, float, float, float]]):
    """``n`` pallets (1.2 x 0.8 m; empty 0.15 m or loaded 0.9-1.4 m high) off the path and the racks."""
    pts = planar.points()[::10]
    out: list[tuple[float, float, float, float, float]] = []
    for _ in range(200 * max(n, 1)):
        if len(out) >= n:
            break
        x, y = rng.uniform(-half + 1.0, half - 1.0, 2)
        sx, sy = (1.2, 0.8) if rng.random() < 0.5 else (0.8, 1.2)
        sz = 0.15 if rng.random() < 0.4 else float(rng.uniform(0.9, 1.4))
        if _rect_distance(pts, x, y, sx, sy) < PALLET_CLEARANCE_M:
            continue
        corners = np.array([[x + a * sx / 2, y + b * sy / 2] for a in (-1, 1) for b in (-1, 1)])
        if any(_rect_distance(corners, rx, ry, rsx + 0.4, rsy + 0.4) == 0.0 for rx, ry, rsx, rsy, _ in racks + out):
            continue
        out.append((float(x), float(y), sx, sy, sz))
    return out


def make_warehouse_scene(seed: int, planar: PlanarPath, n_pallets: int, moving: list[MovingBox],
                         floor_contrast: float, extra: list[tuple[float, float, float, float, float]]) -> Scene:
    """A hall around ``planar``: racks, pallets, ``extra`` boxes (kerbs) and a shiny floor."""
    rng = np.random.default_rng(seed + 31)
    half_x = max(15.0, float(np.abs(planar.x).max()) + 6.0)
    half_y = max(15.0, float(np.abs(planar.y).max()) + 6.0)
    racks = place_racks(planar, half_x, half_y)
    pallets = place_pallets(rng, planar, n_pallets, min(half_x, half_y), racks)
    scene = make_room_scene(seed, half_x, half_y, WAREHOUSE_WALL_M, racks + pallets + extra, None, moving,
                            floor_contrast)
    scene.planes[0].gloss = WAREHOUSE_FLOOR_GLOSS
    return scene

