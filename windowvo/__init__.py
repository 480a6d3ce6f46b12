"""windowvo: sliding-window visual odometry for ground robots.

OpenCV front end (tracks with persistent ids, RANSAC, keyframes, quality gates), GTSAM
fixed-lag smoother back end (projection factors under Huber, wheel-odometry factors with online
calibration, ground-plane factors at the camera's known height, soft roll/pitch prior), Rerun viewer.
Entry points: ``python -m windowvo.run`` (files), ``windowvo.Odometry`` (a robot's loop).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"
__all__ = ["CameraModel", "Odometry", "__version__"]

if TYPE_CHECKING:  # pragma: no cover
    from .camera import CameraModel
    from .runtime.stream import Odometry


def __getattr__(name: str) -> Any:
    # Lazy: `import windowvo` stays cheap for the command-line tools that do not need GTSAM.
    if name == "Odometry":
        from .runtime.stream import Odometry

        return Odometry
    if name == "CameraModel":
        from .camera import CameraModel

        return CameraModel
    raise AttributeError(f"module 'windowvo' has no attribute {name!r}")
