"""Calibrated camera model: pinhole with optional radial-tangential or equidistant distortion.

All functions are vectorised over N points given as ``(N, 2)`` pixels or ``(N, 3)`` points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import CalibrationError
from .types import DistortionModel


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: DistortionModel = DistortionModel.NONE
    distortion: tuple[float, ...] = ()
    T_base_cam: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"camera: width and height must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise CalibrationError(f"camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise CalibrationError(
                f"camera: principal point ({self.cx}, {self.cy}) lies outside the {self.width}x{self.height} image"
            )
        n = len(self.distortion)
        if not all(np.isfinite(d) for d in self.distortion):
            raise CalibrationError("camera: distortion coefficients must be finite numbers")
        if not all(np.isfinite(v) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise CalibrationError("camera: fx, fy, cx, cy must be finite")
        model = DistortionModel(self.distortion_model)
        object.__setattr__(self, "distortion_model", model)
        if model is DistortionModel.NONE and any(abs(d) > 0 for d in self.distortion):
            raise CalibrationError("camera: distortion coefficients given but distortion_model is 'none'")
        if model is DistortionModel.RADTAN and n not in (4, 5):
            raise CalibrationError(f"camera: radtan distortion needs 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {n}")
        if model is DistortionModel.EQUIDISTANT and n != 4:
            raise CalibrationError(f"camera: equidistant distortion needs 4 coefficients (k1 k2 k3 k4), got {n}")
        T = np.asarray(self.T_base_cam, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise CalibrationError("camera: T_base_cam must be 16 finite numbers (a 4x4 matrix, row major)")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
            raise CalibrationError("camera: T_base_cam is not a rigid transform (rotation not orthonormal)")
        if np.linalg.det(R) < 0:
            raise CalibrationError("camera: T_base_cam is a reflection (rotation determinant -1), not a rigid transform: "
                                   "one axis is flipped (a left-handed frame)")
        object.__setattr__(self, "T_base_cam", T)

    # ------------------------------------------------------------------ matrices
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        """False only for an ideal pinhole (a fisheye is never one, even with zero coefficients)."""
        if self.distortion_model is DistortionModel.EQUIDISTANT:
            return True
        return self.distortion_model is not DistortionModel.NONE and any(abs(d) > 0 for d in self.distortion)

    # ------------------------------------------------------------------ pixels <-> rays
    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points (N,3) to distorted pixels (N,2).

        Pinhole and radtan need Z > 0; the equidistant (fisheye) model projects any direction
        but the optical axis' opposite, so points beside and behind the lens plane work too.
        """
        p = np.asarray(p_cam, dtype=float).reshape(-1, 3)
        if self.distortion_model is DistortionModel.EQUIDISTANT:
            return self._project_equidistant(p)
        xn = p[:, :2] / p[:, 2:3]
        return self.distort_normalized(xn)

    def _equidistant_theta_d(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.distortion if self.distortion else (0.0, 0.0, 0.0, 0.0)
        t2 = theta * theta
        return theta * (1 + k1 * t2 + k2 * t2 * t2 + k3 * t2**3 + k4 * t2**4)

    def _equidistant_theta(self, theta_d: np.ndarray) -> np.ndarray:
        """Off-axis angle theta of the ray that the lens maps to radius ``theta_d`` (Newton)."""
        k1, k2, k3, k4 = self.distortion if self.distortion else (0.0, 0.0, 0.0, 0.0)
        theta = np.array(theta_d, dtype=float, copy=True)
        for _ in range(30):
            t2 = theta * theta
            f = self._equidistant_theta_d(theta) - theta_d
            df = 1 + 3 * k1 * t2 + 5 * k2 * t2 * t2 + 7 * k3 * t2**3 + 9 * k4 * t2**4
            step = f / np.where(np.abs(df) > 1e-12, df, 1e-12)
            theta -= step
            if np.all(np.abs(step) < 1e-13):
                break
        return theta

    def _project_equidistant(self, p: np.ndarray) -> np.ndarray:
        r = np.hypot(p[:, 0], p[:, 1])
        theta = np.arctan2(r, p[:, 2])  # 0 on the optical axis, up to pi behind the camera
        scale = np.where(r > 1e-15, self._equidistant_theta_d(theta) / np.maximum(r, 1e-15), 0.0)
        return np.stack([self.fx * p[:, 0] * scale + self.cx, self.fy * p[:, 1] * scale + self.cy], axis=1)

    def distort_normalized(self, xn: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (N,2) to distorted pixels (N,2)."""
        xn = np.asarray(xn, dtype=float).reshape(-1, 2)
        if self.distortion_model is DistortionModel.EQUIDISTANT:
            return self._project_equidistant(np.concatenate([xn, np.ones((len(xn), 1))], axis=1))
        x, y = xn[:, 0], xn[:, 1]
        d = self.distortion
        if not self.has_distortion:
            xd, yd = x, y
        else:  # radtan
            k1, k2, p1, p2 = d[:4]
            k3 = d[4] if len(d) > 4 else 0.0
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)

    def undistort_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to normalised undistorted coordinates (N,2).

        A ray 90 degrees or more off the optical axis (only a fisheye sees one) has no
        normalised coordinates: its row is nan. Use :meth:`unproject` for such lenses.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        if self.distortion_model is DistortionModel.EQUIDISTANT:
            b = self.unproject(uv.reshape(-1, 2))
            with np.errstate(divide="ignore", invalid="ignore"):
                out = b[:, :2] / b[:, 2:3]
            out[b[:, 2] <= 1e-12] = np.nan
            return out
        if not self.has_distortion:
            return (uv.reshape(-1, 2) - [self.cx, self.cy]) / [self.fx, self.fy]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        return cv2.undistortPoints(uv, self.K, self.dist_coeffs, criteria=crit).reshape(-1, 2)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels to the pixels an ideal pinhole camera with the same K would see."""
        xn = self.undistort_normalized(uv)
        return xn * [self.fx, self.fy] + [self.cx, self.cy]

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to unit bearing vectors (N,3) in the camera frame.

        For the equidistant model the bearing comes from the off-axis angle theta and the
        azimuth phi of the pixel, so rays 90 degrees or more off the axis are represented.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.distortion_model is DistortionModel.EQUIDISTANT:
            xd = (uv[:, 0] - self.cx) / self.fx
            yd = (uv[:, 1] - self.cy) / self.fy
            theta_d = np.hypot(xd, yd)
            theta = self._equidistant_theta(theta_d)
            s = np.where(theta_d > 1e-15, np.sin(theta) / np.maximum(theta_d, 1e-15), 1.0)
            return np.stack([xd * s, yd * s, np.cos(theta)], axis=1)
        xn = self.undistort_normalized(uv)
        rays = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def ray_angle(self, uv: np.ndarray) -> np.ndarray:
        """Angle (rad) between the optical axis and the ray seen at each distorted pixel (N,)."""
        return np.arccos(np.clip(self.unproject(uv)[:, 2], -1.0, 1.0))

    def undistortion_jacobian(self, uv: np.ndarray) -> np.ndarray:
        """d(undistorted pinhole pixel) / d(distorted pixel) at each pixel, (N, 2, 2).

        It tells how pixel noise measured in the image is stretched in the pinhole pixels
        the back end uses. Computed as the inverse of the distortion's Jacobian (central
        differences of :meth:`distort_normalized`) at the undistorted point; nan for rays
        90 degrees or more off the axis.
        """
        xn = self.undistort_normalized(uv)
        h = 1e-6
        J = np.empty((len(xn), 2, 2))
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            # d(distorted px) / d(normalised coordinate j)
            J[:, :, j] = (self.distort_normalized(xn + e) - self.distort_normalized(xn - e)) / (2 * h)
        f = np.array([self.fx, self.fy])
        J /= f[None, None, :]  # per pinhole pixel instead of per normalised unit
        out = np.full_like(J, np.nan)
        ok = np.all(np.isfinite(J), axis=(1, 2)) & (np.abs(np.linalg.det(np.where(np.isfinite(J), J, 0.0))) > 1e-12)
        out[ok] = np.linalg.inv(J[ok])
        return out

    def pixel_grid(self) -> np.ndarray:
        """Every pixel centre (H*W, 2) as (u, v), row by row."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return np.stack([u.ravel(), v.ravel()], axis=1)

    def pixel_bearings(self) -> np.ndarray:
        """Unit bearing vectors (H*W, 3) through every pixel centre, distortion included."""
        return self.unproject(self.pixel_grid())

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv).reshape(-1, 2)
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 0] <= self.width - 1 - margin)
            & (uv[:, 1] <= self.height - 1 - margin)
        )

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "distortion_model": self.distortion_model.value,
            "distortion": [float(d) for d in self.distortion],
            "T_base_cam": [float(x) for x in np.asarray(self.T_base_cam).ravel()],
        }
