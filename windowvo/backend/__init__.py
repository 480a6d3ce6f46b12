"""Back end: GTSAM fixed-lag smoother over keyframe poses and landmarks."""
