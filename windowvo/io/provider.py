"""Data provider: reads frames in order and screens out unusable ones.

Black frames, exact duplicates (a frozen camera driver) and unreadable files are reported
and skipped; timestamp gaps (dropped frames) are reported and processing goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..config import InputChecksConfig
from ..errors import FrameError
from ..runtime.stage_timer import Stage, begin_frame, end_frames, section
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
        prefetch: int = 0,
    ):
        self.seq = seq
        self.checks = checks
        self.n = len(seq) if max_frames is None else min(len(seq), max_frames)
        self.mask_folder = mask_folder
        dts = np.diff(seq.timestamps[: self.n])
        self.nominal_dt = float(np.median(dts)) if len(dts) else 0.0
        self._prev_img: np.ndarray | None = None
        # Frames decoded ahead by a thread (image decoding releases the GIL, so it overlaps with tracking).
        self.prefetch = prefetch

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

    def _images(self) -> Iterator[tuple[int, np.ndarray | FrameError]]:
        """Decoded frames in order: here, or from a decoding thread running ``prefetch`` frames ahead (a frame
        decoded here starts that frame's stage times, ``runtime/stage_timer.py``)."""
        if self.prefetch <= 0:
            for i in range(self.n):
                begin_frame(i)
                try:
                    with section(Stage.DECODE):
                        img = self.seq.read_image(i)
                except FrameError as err:
                    yield i, err
                    continue
                yield i, img
            end_frames()
            return
        q: queue.Queue = queue.Queue(maxsize=self.prefetch)
        stop = threading.Event()

        def decode() -> None:
            for i in range(self.n):
                try:
                    item: np.ndarray | FrameError | BaseException = self.seq.read_image(i)
                except FrameError as err:
                    item = err
                except BaseException as err:  # handed over, raised in the reading thread
                    item = err
                while not stop.is_set():
                    try:
                        q.put((i, item), timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if stop.is_set() or (isinstance(item, BaseException) and not isinstance(item, FrameError)):
                    return

        worker = threading.Thread(target=decode, name="windowvo-decode", daemon=True)
        worker.start()
        try:
            for _ in range(self.n):
                i, item = q.get()
                if isinstance(item, BaseException) and not isinstance(item, FrameError):
                    raise item
                yield i, item
        finally:
            stop.set()

    def __iter__(self) -> Iterator[Frame | SkippedFrame]:
        """The frames in order, named by their index in the whole sequence (``seq.first_frame`` on: a
        sub-sequence's frames keep their indices)."""
        ts = self.seq.timestamps
        first = self.seq.first_frame
        for i, img_or_err in self._images():
            t, idx = float(ts[i]), first + i
            if i > 0 and self.nominal_dt > 0 and ts[i] - ts[i - 1] > self.checks.max_time_gap_factor * self.nominal_dt:
                gap = ts[i] - ts[i - 1]
                log.warning("timestamp gap of %.3f s before frame %d (about %d frames dropped)", gap, idx,
                            int(round(gap / self.nominal_dt)) - 1)
            if isinstance(img_or_err, FrameError):
                yield SkippedFrame(idx, t, str(img_or_err))
                continue
            img = img_or_err
            with section(Stage.INPUT_CHECKS):
                mean = float(cv2.mean(img)[0])  # OpenCV's: a tenth of numpy's time on a 640x480 frame
                black = mean < self.checks.black_frame_mean
                duplicate = not black and self._prev_img is not None and np.array_equal(img, self._prev_img)
            if black:
                yield SkippedFrame(idx, t, f"frame {idx}: black frame (mean {mean:.1f})")
                continue
            if duplicate:
                yield SkippedFrame(idx, t, f"frame {idx}: exact duplicate of the previous frame")
                continue
            self._prev_img = img
            with section(Stage.DECODE):
                mask = self._mask(i)
            yield Frame(idx, t, img, mask)
