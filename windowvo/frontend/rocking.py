"""Whether the base rocks on its suspension, told by vision in the run's first moving frames (``frontend.rocking_*``).

With wheel odometry the tracker detects new corners in the image's top rows first (``detection_order: auto`` ->
``rows``): the wheels and the floor's region carry the scale, and a road's kerbs and grass, which a floor plane fit
would take for the road, cannot. That holds while the floor keeps its attitude against the base. A base rocking on
its suspension tilts against its floor by a degree and more between keyframes; the floor's points are then what
measures each keyframe's tilt against the floor, and the floor's region, measured on the estimate's tilt, reads the
steps short or long by a few per cent (docs/scale_suite.md, "Floor corners for a rocking base"). So with wheels a
rocking base gets the floor its corners (``spread``): fused 0.81x on the scale suite's five rocking runs, 0.62x on
twelve held out, but a rocking straight street 1.8-2.0x.

The decision is taken once, on the run's first ``rocking_frames`` frames that move: switched later, the window holds
the top rows' landmarks for its whole length and most of the gain is lost (stop 61's switch on the back end's rocking
test, measured). The test: vision's rotation between consecutive frames (essential matrix of their shared tracks),
its part about the base's horizontal axes (``T_base_cam``) as a rate; the base rocks when the median rate exceeds
``rocking_rate_deg_s``. Measured on the first frames: the level rendered runs 0.04-0.15 deg/s, KITTI 06 and 01 (a
real car) 0.39 and 1.92, the rendered suspensions (0.7-2 deg at 1.7-5.1 Hz) 5.3-27.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .gates import MIN_COMMON_TRACKS
from .two_view import essential_ransac, recover_relative_pose

# The note the run's stats.csv carries at the frame the base is found rocking (``summary.json``'s
# ``corners_spread_from_frame`` finds it there).
ROCKING_NOTE = "the base rocks on its suspension"
# Frames whose tracks moved less than this since the last one (median, pixels) tell no rotation from the essential
# matrix reliably (nor does a base at rest rock): they are not counted.
MIN_FLOW_PX = 1.0


@dataclass
class RockingCheck:
    """Vision's tilt rate over the first moving frames and the decision it gives (``observe``)."""

    R_base_cam: np.ndarray
    focal: float
    frames: int  # frontend.rocking_frames: the moving frames judged
    rate_deg_s: float  # frontend.rocking_rate_deg_s: the median tilt rate above which the base rocks
    threshold_px: float = 0.5  # the essential matrix's RANSAC threshold (frontend.ransac_threshold_px)
    confidence: float = 0.999
    rates: list[float] = field(default_factory=list)  # deg/s, one per moving frame judged
    rocks: bool | None = None  # None until decided

    def observe(self, dt: float, prev_ids: np.ndarray | None, prev_xn: np.ndarray | None, ids: np.ndarray,
                xn: np.ndarray, flow_px: float) -> bool:
        """One frame, ``dt`` seconds after the last (its shared tracks' rays ``prev_xn`` then, ``xn`` now, and their
        median ``flow_px``). True once: at the frame that decides the base rocks."""
        if self.rocks is not None or prev_ids is None or prev_xn is None or not dt > 0:
            return False
        if not flow_px >= MIN_FLOW_PX:
            return False
        rate = self._tilt_rate(dt, prev_ids, prev_xn, ids, xn)
        if rate is None:
            return False
        self.rates.append(rate)
        if len(self.rates) < self.frames:
            return False
        self.rocks = bool(np.median(self.rates) > self.rate_deg_s)
        return self.rocks

    @property
    def median_rate_deg_s(self) -> float:
        return float(np.median(self.rates)) if self.rates else float("nan")

    def _tilt_rate(self, dt: float, prev_ids: np.ndarray, prev_xn: np.ndarray, ids: np.ndarray,
                   xn: np.ndarray) -> float | None:
        """The rotation between the two frames about the base's horizontal axes, deg/s; None: not measured."""
        _, i_cur, i_prev = np.intersect1d(ids, prev_ids, assume_unique=True, return_indices=True)
        if len(i_cur) < MIN_COMMON_TRACKS:
            return None
        a, b = prev_xn[i_prev].astype(np.float64), xn[i_cur].astype(np.float64)
        res = recover_relative_pose(essential_ransac(a, b, self.focal, self.threshold_px, self.confidence), a, b,
                                    self.focal)
        if res.R_cur_kf is None:
            return None
        w_base = self.R_base_cam @ cv2.Rodrigues(res.R_cur_kf)[0].ravel()
        return float(np.degrees(np.hypot(w_base[0], w_base[1])) / dt)
