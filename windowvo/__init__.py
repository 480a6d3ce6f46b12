"""windowvo: sliding-window visual odometry for ground robots.

OpenCV front end (tracks with persistent ids, RANSAC, keyframes, quality gates), GTSAM
fixed-lag smoother back end (projection factors under Huber, wheel-odometry between-factors,
soft roll/pitch prior), Rerun viewer. Entry point: ``python -m windowvo.run``.
"""

__version__ = "0.1.0"
