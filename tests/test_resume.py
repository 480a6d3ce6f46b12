"""The pieces ``--resume`` continues a killed run with: a sub-sequence that keeps the whole sequence's frame indices,
and the seam that places a continuation (its own world and, without a metric cue, its own scale) in the killed
run's world. The command line end to end (SIGKILL, --resume, a kill during --resume) is in tests/test_faults.py."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from windowvo.camera import CameraModel
from windowvo.config import InputChecksConfig
from windowvo.errors import SequenceError
from windowvo.geometry import inv_T
from windowvo.io.odometry import WheelOdometry
from windowvo.io.provider import DataProvider
from windowvo.io.sequence import Sequence, subsequence
from windowvo.runtime.journal import JournalContents, continued, overlap_scale, seam
from windowvo.types import FrameRecord


@pytest.fixture
def seq(tmp_path) -> Sequence:
    """Six 16x12 frames 0.1 s apart (each a different grey), wheel samples every 0.03 s along x at 1 m/s."""
    paths = []
    for i in range(6):
        p = tmp_path / f"{i:06d}.png"
        cv2.imwrite(str(p), np.full((12, 16), 40 + 30 * i, np.uint8))
        paths.append(p)
    t_odo = np.arange(0.0, 0.6, 0.03)
    odo = WheelOdometry(t_odo, t_odo.copy(), np.zeros_like(t_odo), np.zeros_like(t_odo))
    cam = CameraModel(16, 12, 20.0, 20.0, 8.0, 6.0)
    return Sequence(tmp_path, paths, np.arange(6) * 0.1, cam, odometry=odo)


def test_a_subsequence_keeps_the_frame_indices_of_the_whole_sequence(seq):
    sub = subsequence(seq, 3)
    assert len(sub) == 3 and sub.first_frame == 3
    np.testing.assert_array_equal(sub.timestamps, seq.timestamps[3:])
    frames = list(DataProvider(sub, InputChecksConfig()))
    assert [f.index for f in frames] == [3, 4, 5]
    for f in frames:
        np.testing.assert_array_equal(f.image, seq.read_image(f.index))
    # The wheels start at the last sample at or before frame 3: the pose there is interpolated, as in the whole.
    assert sub.odometry is not None and sub.odometry.timestamps[0] <= 0.3 < sub.odometry.timestamps[1]
    for t in (0.3, 0.41, 0.5):
        np.testing.assert_allclose(sub.odometry.pose_at(t), seq.odometry.pose_at(t))
    subsub = subsequence(sub, 1, 2)
    assert subsub.first_frame == 4 and len(subsub) == 1
    assert [f.index for f in DataProvider(subsub, InputChecksConfig())] == [4]


def test_a_subsequence_out_of_range_is_refused(seq):
    with pytest.raises(SequenceError):
        subsequence(seq, 6)


def _record(i: int, keyframe: bool) -> FrameRecord:
    return FrameRecord(i, 0.1 * i, 100, 90, 120, 5.0, 5.0, 0.9, 1.0, 0.5, keyframe, "parallax" if keyframe else "",
                       "", "ok" if keyframe else "", 50, 0.5, 10.0, 20.0 if keyframe else 0.0)


def _pose(i: int) -> np.ndarray:
    """A base driving an arc: 0.1 m per frame, turning 2 degrees per frame."""
    yaw = np.radians(2.0 * i)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = [sum(0.1 * np.cos(np.radians(2.0 * j)) for j in range(i)),
                sum(0.1 * np.sin(np.radians(2.0 * j)) for j in range(i))]
    return T


def _run(frames: range, every: int, T_world_first: np.ndarray, scale: float) -> JournalContents:
    """A run's journal: keyframes every ``every`` frames, causal poses held at the last keyframe, in a world of
    its own (``T_world_first``: its first frame's pose) and its own unit (``scale`` m per unit)."""
    j = JournalContents({"use_odometry": False, "use_ground": False}, first_frame=frames[0])
    held = None
    for i in frames:
        kf = (i - frames[0]) % every == 0
        if kf:
            held = inv_T(_pose(frames[0])) @ _pose(i)
            held[:3, 3] /= scale
            held = T_world_first @ held
        j.records.append(_record(i, kf))
        j.online.append(held)
        j.wheel_m.append(None)
    return j


def test_the_seam_scales_and_places_a_monocular_continuation():
    base = _run(range(0, 21), 2, np.eye(4), 1.0)
    base.final_keyframes = {i: (0.1 * i, _pose(i)) for i in (0, 2, 4, 6)}
    cont = _run(range(6, 30), 3, np.eye(4), 2.5)  # its own world (base at frame 6), 2.5 m per unit
    sm = seam(base, 6, cont.records, cont.online)
    assert sm.n_prefix == 7
    assert sm.scale == pytest.approx(2.5, rel=0.01)
    for i in (12, 18, 27):  # continuation keyframes, placed in the killed run's world
        np.testing.assert_allclose(sm.place(cont.online[i - 6]), _pose(i), atol=0.01 * np.linalg.norm(_pose(i)[:3, 3]))
    whole = continued(base, cont)
    assert [r.frame_index for r in whole.records] == list(range(30))
    assert whole.resumed_from == [6] and 6 in whole.final_keyframes


def test_a_metric_run_is_not_rescaled():
    base = _run(range(0, 21), 2, np.eye(4), 1.0)
    base.header = {"use_odometry": True, "use_ground": False}
    base.final_keyframes = {6: (0.6, _pose(6))}
    cont = _run(range(6, 30), 3, np.eye(4), 2.5)
    assert seam(base, 6, cont.records, cont.online).scale == 1.0
    assert overlap_scale(base, 6, cont.records, cont.online) == pytest.approx(2.5, rel=0.01)  # what it would fit

