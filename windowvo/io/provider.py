"""Data provider: reads frames in order and screens out unusable ones.

Black frames, exact duplicates (a frozen camera driver) and unreadable files are reported
and skipped; timestamp gaps (dropped frames) are reported and processing goes on.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..config import InputChecksConfig
from ..errors import FrameError
from ..types import Frame
from .sequence import Sequence

log = logging.getLogger(__name__)


@dataclass
class SkippedFrame:
    index: int
    timestamp: float
    reason: str


class DataProvider:
    def __init__(
        self,
        seq: Sequence,
        checks: InputChecksConfig,
        max_frames: int | None = None,
        mask_folder: Path | None = None,
    ):
        self.seq = seq
        self.checks = checks
        self.n = len(seq) if max_frames is None else min(len(seq), max_frames)
        self.mask_folder = mask_folder
        dts = np.diff(seq.timestamps[: self.n])
        self.nominal_dt = float(np.median(dts)) if len(dts) else 0.0
        self._prev_img: np.ndarray | None = None

    def __len__(self) -> int:
        return self.n

    def _mask(self, i: int) -> np.ndarray | None:
        if self.mask_folder is None:
            return None
        name = self.seq.frame_name(i)
        p = self.mask_folder / name
        if not p.is_file():
            return None
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is None or m.shape != (self.seq.camera.height, self.seq.camera.width):
            log.warning("mask %s unreadable or of the wrong size; ignored", p.name)
            return None
        return m

    def __iter__(self) -> Iterator[Frame | SkippedFrame]:
        ts = self.seq.timestamps
        for i in range(self.n):
            t = float(ts[i])
            if i > 0 and self.nominal_dt > 0 and ts[i] - ts[i - 1] > self.checks.max_time_gap_factor * self.nominal_dt:
                gap = ts[i] - ts[i - 1]
                log.warning("timestamp gap of %.3f s before frame %d (about %d frames dropped)", gap, i,
                            int(round(gap / self.nominal_dt)) - 1)
            try:
                img = self.seq.read_image(i)
            except FrameError as err:
                yield SkippedFrame(i, t, str(err))
                continue
            if float(img.mean()) < self.checks.black_frame_mean:
                yield SkippedFrame(i, t, f"frame {i}: black frame (mean {img.mean():.1f})")
                continue
            if self._prev_img is not None and np.array_equal(img, self._prev_img):
                yield SkippedFrame(i, t, f"frame {i}: exact duplicate of the previous frame")
                continue
            self._prev_img = img
            yield Frame(i, t, img, self._mask(i))
