"""Ground-robot paths: planar (x, y, yaw) profiles sampled densely in time."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from . import exact

DENSE_HZ = 200.0


class PathKind(str, enum.Enum):
    LOOP = "loop"
    FIGURE_EIGHT = "figure_eight"
    STRAIGHT = "straight"
    TURN_IN_PLACE = "turn_in_place"
    STOP_AND_GO = "stop_and_go"
    RAMP = "ramp"


@dataclass
class PlanarPath:
    """Dense planar states of the base; interpolated at any time."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray  # unwrapped

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def at(self, t: np.ndarray | float):
        return (
            np.interp(t, self.t, self.x),
            np.interp(t, self.t, self.y),
            np.interp(t, self.t, self.yaw),
        )

    def points(self) -> np.ndarray:
        return np.stack([self.x, self.y], axis=1)


def _follow_curve(curve_xy: np.ndarray, speed_profile: np.ndarray, dt: float) -> PlanarPath:
    """Drive along a densely sampled curve with the given speed at each time step."""
    seg = np.linalg.norm(np.diff(curve_xy, axis=0), axis=1)
    s_curve = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.concatenate([[0.0], np.cumsum(speed_profile[:-1] * dt)])
    s = np.minimum(s, s_curve[-1])
    x = np.interp(s, s_curve, curve_xy[:, 0])
    y = np.interp(s, s_curve, curve_xy[:, 1])
    # Heading is the curve tangent at the arclength s (defined also while stopped).
    tang = np.gradient(curve_xy, s_curve, axis=0)
    yaw_curve = np.unwrap(exact.arctan2(tang[:, 1], tang[:, 0]))
    yaw = np.interp(s, s_curve, yaw_curve)
    t = np.arange(len(s)) * dt
    return PlanarPath(t, x, y, yaw)


def _loop(kind: PathKind, duration: float, speed: float, size: float, n: int, dt: float) -> PlanarPath:
    """A circle of radius ``size`` (centre at the origin, starting at (0, -size) heading +x)."""
    v = np.full(n, speed)
    length = speed * duration + 1.0
    phi = np.linspace(0, length / size, int(length * 200) + 2)
    curve = np.stack([size * np.sin(phi), size * (1 - np.cos(phi)) - size], axis=1)
    if kind is PathKind.STOP_AND_GO:
        tt = np.arange(n) * dt
        # 5 s driving, 3 s standing, repeated; smooth ramps of 0.5 s.
        cyc = np.mod(tt, 8.0)
        ramp_up = np.clip(cyc / 0.5, 0, 1)
        ramp_dn = np.clip((5.0 - cyc) / 0.5, 0, 1)
        v = speed * np.minimum(ramp_up, ramp_dn) * (cyc < 5.0)
    return _follow_curve(curve, v, dt)


def _figure_eight(duration: float, speed: float, size: float, n: int, dt: float) -> PlanarPath:
    length = speed * duration + 1.0
    phi = np.linspace(0, 2 * np.pi * 4, 40000)
    a = size * 1.3
    curve = np.stack([a * np.sin(phi), a * np.sin(phi) * np.cos(phi)], axis=1)
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    cum = np.concatenate([[0], np.cumsum(seg)])
    curve = curve[cum <= length]
    return _follow_curve(curve, np.full(n, speed), dt)


def _straight(duration: float, speed: float, size: float, n: int, dt: float) -> PlanarPath:
    """Along x, centred on the origin, swaying 0.3 m sideways with a wavelength of 2 pi 3 m x (size / 4.5)."""
    length = speed * duration + 0.5
    x = np.linspace(-length / 2, length / 2, int(length * 200) + 2)
    curve = np.stack([x, 0.3 * np.sin(x / (3.0 * (size / 4.5)))], axis=1)
    return _follow_curve(curve, np.full(n, speed), dt)


def _ramp_stadium(duration: float, speed: float, n: int, dt: float) -> PlanarPath:
    """A stadium loop along x: up the ramp (which spans the room's width), a U-turn on the plateau,
    back down, a U-turn below, and so on."""
    straight, r = 12.0, 2.5
    pts = []
    for _lap in range(int(speed * duration / (2 * straight + 2 * np.pi * r)) + 2):
        x = np.linspace(-straight / 2, straight / 2, 1200)
        pts.append(np.stack([x, np.zeros_like(x)], axis=1))
        ang = np.linspace(np.pi / 2, -np.pi / 2, 800)
        pts.append(np.stack([straight / 2 + r * np.cos(ang), -r + r * np.sin(ang)], axis=1))
        pts.append(np.stack([x[::-1], np.full_like(x, -2 * r)], axis=1))
        ang = np.linspace(-np.pi / 2, -3 * np.pi / 2, 800)
        pts.append(np.stack([-straight / 2 + r * np.cos(ang), -r + r * np.sin(ang)], axis=1))
    curve = np.concatenate(pts)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(curve, axis=0), axis=1) > 1e-9])
    return _follow_curve(curve[keep], np.full(n, speed), dt)


def _turn_in_place(duration: float, speed: float, n: int, dt: float) -> PlanarPath:
    """Drive, spin a full turn in place, drive on."""
    t = np.arange(n) * dt
    t_drive = duration * 0.3
    t_spin = duration - 2 * t_drive
    x = np.zeros(n)
    yaw = np.zeros(n)
    p1 = t < t_drive
    x[p1] = -3.0 + speed * t[p1]
    sp = (t >= t_drive) & (t < t_drive + t_spin)
    x[sp] = -3.0 + speed * t_drive
    yaw[sp] = 2 * np.pi * (0.5 - 0.5 * np.cos(np.pi * (t[sp] - t_drive) / t_spin))
    p3 = t >= t_drive + t_spin
    x[p3] = -3.0 + speed * t_drive + speed * (t[p3] - t_drive - t_spin)
    yaw[p3] = 2 * np.pi
    return PlanarPath(t, x, np.zeros(n), yaw)


def make_path(kind: PathKind, duration: float, speed: float = 1.0, size: float = 4.5) -> PlanarPath:
    """Path of the given kind lasting ``duration`` seconds at ``speed`` m/s.

    ``size`` scales the curves: the loop's radius, the figure eight's half width / 1.3 and the
    straight's sway wavelength (4.5: room-sized). The ramp and the turn in place ignore it.
    """
    kind = PathKind(kind)
    dt = 1.0 / DENSE_HZ
    n = round(duration * DENSE_HZ) + 1
    if kind in (PathKind.LOOP, PathKind.STOP_AND_GO):
        return _loop(kind, duration, speed, size, n, dt)
    if kind is PathKind.FIGURE_EIGHT:
        return _figure_eight(duration, speed, size, n, dt)
    if kind is PathKind.STRAIGHT:
        return _straight(duration, speed, size, n, dt)
    if kind is PathKind.RAMP:
        return _ramp_stadium(duration, speed, n, dt)
    if kind is PathKind.TURN_IN_PLACE:
        return _turn_in_place(duration, speed, n, dt)
    raise ValueError(f"unknown path kind {kind}")
