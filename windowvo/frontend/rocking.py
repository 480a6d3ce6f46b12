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
test, measured). The test: vision's rotation between two frames at least ``MIN_INTERVAL_S`` apart (consecutive ones
at 10-20 Hz; the essential matrix of their shared tracks, the smaller of its two rotations: over so short a baseline
the cheirality test sometimes picks the one half a turn off), its part about the base's horizontal axes
(``T_base_cam``) as a rate; the base rocks when the median rate exceeds ``rocking_rate_deg_s``. Measured on the
first frames: the level rendered runs 0.04-0.15 deg/s, KITTI 06 and 01 (a real car) 0.39 and 1.92, the rendered
suspensions (0.7-2 deg at 1.7-5.1 Hz) 5.3-27.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .gates import MIN_COMMON_TRACKS
from .two_view import essential_ransac

# The note the run's stats.csv carries at the frame the base is found rocking (``summary.json``'s
# ``corners_spread_from_frame`` finds it there).
ROCKING_NOTE = "the base rocks on its suspension"
# Two frames whose shared tracks moved less than this (median, pixels of the ideal pinhole camera) tell no rotation
# from the essential matrix reliably (nor does a base at rest rock): the pair is not counted.
MIN_FLOW_PX = 1.0
# The frames compared are at least this far apart (s): consecutive frames at 10-20 Hz; at a higher frame rate the
# per-frame angle's noise would weigh more in the rate, and a slow robot's per-frame motion stay under MIN_FLOW_PX.
MIN_INTERVAL_S = 0.045


def smaller_rotation(E: np.ndarray) -> np.ndarray:
    """The one of an essential matrix's two rotations that turns less (``cv2.decomposeEssentialMat``): between frames
    a fraction of a second apart the camera turns by a few degrees at most, the other is half a turn off."""
    R1, R2, _ = cv2.decomposeEssentialMat(E)
    return R1 if np.trace(R1) >= np.trace(R2) else R2


@dataclass
class RockingCheck:
    """Vision's tilt rate over the first moving frames and the decision it gives (``observe``)."""

    R_base_cam: np.ndarray
    focal: float
    frames: int  # frontend.rocking_frames: the frame pairs judged
    threshold_deg_s: float  # frontend.rocking_rate_deg_s: the median tilt rate above which the base rocks
    ransac_threshold_px: float = 0.5  # the essential matrix's RANSAC threshold (frontend.ransac_threshold_px)
    ransac_confidence: float = 0.999
    rates_deg_s: list[float] = field(default_factory=list)  # one per frame pair judged
    rocks: bool | None = None  # None until decided
    _ref: tuple[float, np.ndarray, np.ndarray] | None = None  # (time, track ids, rays) of the frame compared against

    def observe(self, t: float, ids: np.ndarray, xn: np.ndarray) -> bool:
        """One frame at time ``t``: its tracks' ids and normalised rays. True once: at the frame that decides the base
        rocks."""
        if self.rocks is not None:
            return False
        if self._ref is None:
            self._ref = (t, ids.copy(), xn.copy())
            return False
        t_ref, ids_ref, xn_ref = self._ref
        if t - t_ref < MIN_INTERVAL_S:
            return False
        self._ref = (t, ids.copy(), xn.copy())
        _, i_cur, i_ref = np.intersect1d(ids, ids_ref, assume_unique=True, return_indices=True)
        if len(i_cur) < MIN_COMMON_TRACKS:
            return False
        rate = self._tilt_rate_deg_s(t - t_ref, xn_ref[i_ref].astype(np.float64), xn[i_cur].astype(np.float64))
        if rate is None:
            return False
        self.rates_deg_s.append(rate)
        if len(self.rates_deg_s) < self.frames:
            return False
        self.rocks = bool(np.median(self.rates_deg_s) > self.threshold_deg_s)
        return self.rocks

    @property
    def median_rate_deg_s(self) -> float:
        return float(np.median(self.rates_deg_s)) if self.rates_deg_s else float("nan")

    def _tilt_rate_deg_s(self, dt: float, xn_ref_shared: np.ndarray, xn_cur_shared: np.ndarray) -> float | None:
        """The rotation between the two frames about the base's horizontal axes, deg/s; None: the pair tells none
        (its tracks moved too little, or no essential matrix)."""
        flow_px = float(np.median(np.linalg.norm(xn_cur_shared - xn_ref_shared, axis=1))) * self.focal
        if not flow_px >= MIN_FLOW_PX:
            return None
        two_view = essential_ransac(xn_ref_shared, xn_cur_shared, self.focal, self.ransac_threshold_px,
                                    self.ransac_confidence)
        if two_view.E is None:
            return None
        R_cur_ref = smaller_rotation(two_view.E)
        w_base = self.R_base_cam @ cv2.Rodrigues(R_cur_ref)[0].ravel()  # the rotation vector in the base's axes
        return float(np.degrees(np.hypot(w_base[0], w_base[1])) / dt)
