"""The .rrd recording of a run, read back through Rerun's Python API (never the CLI)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest
import yaml
from conftest import make_config
from rerun.chunk import RrdReader

from windowvo.backend.report import ScaleReport
from windowvo.errors import WindowVOError
from windowvo.eval.metrics import evaluate
from windowvo.io.sequence import Sequence
from windowvo.runtime.job import JobReport, load_sequence
from windowvo.runtime.outputs import write_outputs
from windowvo.runtime.pipeline import Pipeline, RunResult
from windowvo.types import FrameEstimate
from windowvo.viz.rerun_logger import LEGEND_ROWS_SHARE, RerunLogger, tail_starts, time_columns

N_FRAMES = 80


@dataclass
class Recorded:
    rrd: Path
    out: Path
    seq: Sequence
    pipe: Pipeline
    result: RunResult
    report: JobReport
    chunks: list


def _run(cfg) -> tuple[Sequence, Pipeline, RunResult, JobReport]:
    """What run_job does, keeping the pipeline for its causal poses (``Pipeline.online``)."""
    seq = load_sequence(cfg)
    viewer = RerunLogger(cfg, seq)
    pipe = Pipeline(cfg, seq, viewer=viewer)
    result = pipe.run()
    write_outputs(cfg, result, cfg.output)
    report = JobReport(result, seq)
    assert seq.groundtruth is not None
    report.accuracy = evaluate(seq.groundtruth, result.trajectory)
    viewer.finish(result, report)
    return seq, pipe, result, report


@pytest.fixture(scope="module")
def recorded(short_loop, tmp_path_factory) -> Recorded:
    out = tmp_path_factory.mktemp("rerun_recording")
    cfg = make_config(short_loop, out, viz={"rerun": "save"}, max_frames=N_FRAMES)
    assert cfg.viz.image_every == 1  # the default: the image on every frame
    seq, pipe, result, report = _run(cfg)
    rrd = out / "recording.rrd"
    return Recorded(rrd, out, seq, pipe, result, report, list(RrdReader(str(rrd)).stream()))


def _rows(chunks, entity: str, column: str) -> list[tuple[int, int, object]]:
    """(frame, order, value) of every temporal row of ``entity`` that has ``column``, in logging order."""
    out = []
    order = 0
    for ch in chunks:
        if str(ch.entity_path) != entity or ch.is_static:
            continue
        rb = ch.to_record_batch()
        if column not in rb.schema.names:
            continue
        frames = rb.column("frame").to_pylist()
        for f, v in zip(frames, rb.column(column).to_pylist()):
            if v is not None:
                out.append((f, order, v))
                order += 1
    return sorted(out, key=lambda r: (r[0], r[1]))


def _static(chunks, entity: str) -> dict[str, object]:
    vals: dict[str, object] = {}
    for ch in chunks:
        if str(ch.entity_path) == entity:
            rb = ch.to_record_batch()
            for name in rb.schema.names:
                v = rb.column(name).to_pylist()[-1]
                vals[name] = v[0] if isinstance(v, list) and len(v) == 1 else v
    return vals


def _revealed(chunks, entity: str, frame: int, column: str) -> np.ndarray:
    """The points of a path revealed with time as the viewer shows them at ``frame``: every block
    logged up to then, then the latest tip."""
    blocks = sorted({str(ch.entity_path) for ch in chunks if str(ch.entity_path).startswith(entity + "/b")},
                    key=lambda p: int(p.rsplit("/b", 1)[1]))
    parts = []
    for b in blocks:
        rows = [r for r in _rows(chunks, b, column) if r[0] <= frame]
        if rows:
            parts.append(np.asarray(rows[-1][2], float).reshape(-1, 3))
    tip = [r for r in _rows(chunks, entity + "/tip", column) if r[0] <= frame]
    if tip:
        parts.append(np.asarray(tip[-1][2], float).reshape(-1, 3))
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    # blocks of a line share their end point with the next part
    keep = np.ones(len(pts), bool)
    keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
    return pts[keep]


def _stats(out: Path) -> list[dict[str, str]]:
    with (out / "stats.csv").open() as fh:
        return list(csv.DictReader(fh))


def test_entities_and_jpeg_images(recorded):
    chunks = recorded.chunks
    paths = {str(ch.entity_path) for ch in chunks}
    for expected in ["/world/estimate/base/cam/image", "/world/estimate/base/cam/tracks", "/world/estimate/base",
                     "/world/landmarks", "/world/window", "/world/final", "/world/groundtruth/tip",
                     "/world/wheel_odometry/tip", "/world/estimate/online/tip", "/plots/counts/tracked",
                     "/plots/ms/backend", "/plots/ratios/inliers", "/plots/px/parallax", "/states/gate", "/log",
                     "/legend"]:
        assert expected in paths, (expected, sorted(paths))
    images = _rows(chunks, "/world/estimate/base/cam/image", "EncodedImage:blob")
    assert [r[0] for r in images] == list(range(N_FRAMES))  # the image on every frame
    media = _rows(chunks, "/world/estimate/base/cam/image", "EncodedImage:media_type")
    assert {r[2] if isinstance(r[2], str) else r[2][0] for r in media} == {"image/jpeg"}
    # The JPEG logged at frame 40 is frame 40's image (and not, say, frame 60's).
    blob = images[40][2]
    jpeg = np.frombuffer(bytes(blob[0] if isinstance(blob[0], list) else blob), np.uint8)
    decoded = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
    own = recorded.seq.read_image(40).astype(float)
    other = recorded.seq.read_image(60).astype(float)
    assert decoded.shape == own.shape
    err_own = float(np.mean(np.abs(decoded - own)))
    err_other = float(np.mean(np.abs(decoded - other)))
    assert err_own < 4.0, err_own
    assert err_other > 3 * err_own, (err_own, err_other)


def test_camera_overlays_one_row_per_frame(recorded):
    """The camera items sent as columns (a few frames per send) give each frame its own row: the tracks are that
    frame's tracks (as many as the plotted count, one colour each, the radius once), the outliers and the track
    tails are there on every frame, the last batch included, and the frames' times are the sequence clock."""
    chunks = recorded.chunks
    cam = "/world/estimate/base/cam"
    tracked = {f: int(v[0]) for f, _, v in _rows(chunks, "/plots/counts/tracked", "Scalars:scalars")}
    pos = _rows(chunks, f"{cam}/tracks", "Points2D:positions")
    assert [r[0] for r in pos] == list(range(N_FRAMES))
    assert [len(r[2]) for r in pos] == [tracked[f] for f in range(N_FRAMES)]
    assert len({tuple(map(tuple, r[2])) for r in pos}) > N_FRAMES // 2  # the tracks move: not one row repeated
    colors = _rows(chunks, f"{cam}/tracks", "Points2D:colors")
    assert [len(r[2]) for r in colors] == [len(r[2]) for r in pos]
    assert {tuple(r[2]) for r in _rows(chunks, f"{cam}/tracks", "Points2D:radii")} == {(2.0,)}
    assert [r[0] for r in _rows(chunks, f"{cam}/outliers", "Points2D:positions")] == list(range(N_FRAMES))
    tails = _rows(chunks, f"{cam}/tails", "Arrows2D:vectors")
    assert [r[0] for r in tails] == list(range(N_FRAMES))
    assert max(len(r[2]) for r in tails) > 0
    for ch in chunks:
        if str(ch.entity_path) == f"{cam}/tracks" and not ch.is_static:
            rb = ch.to_record_batch()
            t = np.asarray(rb.column("time").cast(pa.int64()).to_pylist(), float) * 1e-9
            f = rb.column("frame").to_pylist()
            assert np.allclose(t, np.asarray(recorded.seq.timestamps)[f], atol=1e-6)


def test_frustum_is_the_causal_pose(recorded):
    """The pose drawn at each frame is the causal estimate (what the robot had then), not the smoothed one."""
    trans = _rows(recorded.chunks, "/world/estimate/base", "Transform3D:translation")
    by_frame = {f: np.asarray(v, float).reshape(3) for f, _, v in trans}
    assert sorted(by_frame) == list(range(N_FRAMES))
    online = recorded.pipe.online
    for k in (25, 47, N_FRAMES - 1):
        assert np.allclose(by_frame[k], online[k][:3, 3], atol=1e-5), (k, by_frame[k], online[k][:3, 3])
    # ... and it is a good pose: within 5 cm of ground truth in the middle of the run
    gt = recorded.seq.groundtruth.anchored()
    t47 = recorded.seq.timestamps[47]
    j = int(np.argmin(np.abs(gt.timestamps - t47)))
    assert np.linalg.norm(by_frame[47] - gt.positions[j]) < 0.05


def test_paths_revealed_with_time(recorded):
    """At frame k the estimate, ground truth and wheels are drawn up to frame k's time, never beyond."""
    chunks, seq = recorded.chunks, recorded.seq
    k = 59  # the paths' tips are sent every 10 frames: after frames 9, 19, ..., 59
    t_k = float(seq.timestamps[k])
    online = _revealed(chunks, "/world/estimate/online", k, "LineStrips3D:strips")
    expected = np.asarray([T[:3, 3] for T in recorded.pipe.online[: k + 1]])
    assert len(online) == len(expected)
    assert np.allclose(online, expected, atol=1e-5)
    gt = seq.groundtruth.anchored()
    shown = _revealed(chunks, "/world/groundtruth", k, "LineStrips3D:strips")
    assert len(shown) >= 2
    j = int(np.searchsorted(gt.timestamps, t_k + 1e-9, side="right")) - 1
    assert np.allclose(shown[-1], gt.positions[j], atol=1e-5)  # ends at the ground truth of frame k ...
    assert not np.allclose(shown[-1], gt.positions[-1], atol=1e-3)  # ... not at the end of the sequence
    wheels = _revealed(chunks, "/world/wheel_odometry", k, "LineStrips3D:strips")
    assert np.allclose(wheels[-1], seq.odometry.delta(float(seq.timestamps[0]), t_k)[:3, 3], atol=1e-5)
    assert len(wheels) == k + 1
    # the final smoothed trajectory appears only at the last frame, and is trajectory.txt
    final = _rows(chunks, "/world/final", "LineStrips3D:strips")
    assert [r[0] for r in final] == [N_FRAMES - 1]
    assert np.allclose(np.asarray(final[0][2], float).reshape(-1, 3), recorded.result.trajectory.positions, atol=1e-5)


def test_plots_follow_stats_on_the_sequence_clock(recorded):
    chunks = recorded.chunks
    stats = _stats(recorded.out)
    tracked = _rows(chunks, "/plots/counts/tracked", "Scalars:scalars")
    assert [r[0] for r in tracked] == list(range(N_FRAMES))  # buffered columns: every frame, the last batch too
    assert [float(r[2][0]) for r in tracked] == [float(s["n_inliers"]) for s in stats]
    inl = _rows(chunks, "/plots/ratios/inliers", "Scalars:scalars")
    assert np.allclose([r[2][0] for r in inl], [float(s["inlier_ratio"]) for s in stats], atol=1e-4)
    kf_ms = _rows(chunks, "/plots/ms/backend", "Scalars:scalars")
    assert len(kf_ms) == recorded.result.n_keyframes
    # the `time` timeline is the sequence clock
    times = []
    for ch in chunks:
        if str(ch.entity_path) == "/plots/counts/tracked" and not ch.is_static:
            col = ch.to_record_batch().column("time")
            times += (np.asarray(col.cast(pa.int64()).to_pylist(), float) * 1e-9).tolist()
    assert np.allclose(sorted(times), recorded.seq.timestamps[:N_FRAMES], atol=1e-6)


def test_text_log_and_gate_states(recorded):
    chunks = recorded.chunks
    lines = [r[2] for r in _rows(chunks, "/log", "TextLog:text")]
    lines = [v[0] if isinstance(v, list) else v for v in lines]
    kf_lines = [s for s in lines if s.startswith("keyframe at frame")]
    assert len(kf_lines) == recorded.result.n_keyframes
    stats = _stats(recorded.out)
    kf_stats = [s for s in stats if s["is_keyframe"] == "True"]
    for line, s in zip(kf_lines, kf_stats):
        assert line.startswith(f"keyframe at frame {s['frame_index']} ")
        assert f"gate {s['gate']}" in line
    assert any(s.startswith("accuracy: ") for s in lines)
    gates = _rows(chunks, "/states/gate", "StateChange:state")
    assert [r[0] for r in gates] == [int(s["frame_index"]) for s in kf_stats]


def test_recording_properties(recorded):
    chunks, seq = recorded.chunks, recorded.seq
    info = _static(chunks, "/__properties")
    assert seq.root.name in str(info["RecordingInfo:name"])
    props = _static(chunks, "/__properties/sequence")
    assert props["frames"] == N_FRAMES
    assert props["duration_s"] == pytest.approx(seq.timestamps[N_FRAMES - 1] - seq.timestamps[0])
    config = yaml.safe_load(_static(chunks, "/__properties/config")["yaml"])
    assert config["max_frames"] == N_FRAMES
    acc = _static(chunks, "/__properties/accuracy")
    assert acc["summary"] == recorded.report.accuracy.summary()
    assert acc["ate_se3_rmse_m"] == pytest.approx(recorded.report.accuracy.ate_se3_rmse_m)


def _blueprints(rrd: Path) -> list[tuple[list[dict], dict]]:
    """Per blueprint store: its views (class, name, origin, y range, eye) and its time panel."""
    reader = RrdReader(str(rrd))
    stores = reader.blueprints()
    assert stores, "no blueprint in the recording"
    out = []
    for store in stores:
        views: dict[str, dict] = {}
        panel: dict = {}
        for ch in reader.stream(store=store):
            path = str(ch.entity_path)
            rb = ch.to_record_batch()
            cols = {n: rb.column(n).to_pylist()[-1] for n in rb.schema.names}
            if path.startswith("/view/"):
                v = views.setdefault(path.split("/")[2], {})
                for n, val in cols.items():
                    v[n.split(":")[-1]] = val[0] if isinstance(val, list) and len(val) == 1 else val
            elif path == "/time_panel":
                panel.update({n.split(":")[-1]: (val[0] if isinstance(val, list) else val) for n, val in cols.items()})
        out.append(([v for v in views.values() if "class_identifier" in v], panel))
    return out


def test_blueprint_views(recorded):
    """The layout sent at the start and the one sent at the end (with the plots' final y ranges)."""
    stores = _blueprints(recorded.rrd)
    assert len(stores) == 2
    gt_traj = recorded.seq.groundtruth.anchored()
    gt = gt_traj.positions[gt_traj.timestamps <= recorded.seq.timestamps[N_FRAMES - 1] + 1e-6]
    assert len(gt) < len(gt_traj)  # the run covers part of the sequence: the view frames that part
    complete = 0
    for views, panel in stores:
        by_class: dict[str, list[dict]] = {}
        for v in views:
            by_class.setdefault(v["class_identifier"], []).append(v)
        assert [v["space_origin"] for v in by_class["3D"]] == ["world"]
        assert [v["space_origin"] for v in by_class["2D"]] == ["world/estimate/base/cam"]
        assert len(by_class["TimeSeries"]) >= 3
        assert len(by_class["TextLog"]) == 1
        assert panel["timeline"] == "time"
        # top-down on the trajectory: the eye is above the centre of the ground truth's extent over the run
        eye = by_class["3D"][0]
        centre = (gt[:, :2].min(axis=0) + gt[:, :2].max(axis=0)) / 2
        target, position = np.asarray(eye["look_target"]), np.asarray(eye["position"])
        assert np.allclose(target[:2], centre, atol=1e-3)
        extent = float(np.max(gt[:, :2].max(axis=0) - gt[:, :2].min(axis=0)))
        assert position[2] > extent and np.linalg.norm(position[:2] - target[:2]) < 0.01 * position[2]
        # the final layout gives every plot a y range that leaves its top share free for the legend: the
        # plotted data stays below it (the layout sent at the start can only guess the counts' range)
        ranged = [v for v in by_class["TimeSeries"] if v.get("range") is not None]
        if len(ranged) < len(by_class["TimeSeries"]):
            continue
        for v in ranged:
            unit = v["space_origin"].split("/")[-1]
            entities = {str(c.entity_path) for c in recorded.chunks if str(c.entity_path).startswith(f"/plots/{unit}/")}
            values = [r[2][0] for e in entities for r in _rows(recorded.chunks, e, "Scalars:scalars")]
            assert values
            assert np.percentile(values, 99) <= (1 - LEGEND_ROWS_SHARE) * v["range"][1] + 1e-9, (unit, v["range"])
        complete += 1
    assert complete == 1  # the final layout has a range on every plot


def test_skipped_frame_goes_to_the_text_log(short_loop, tmp_path):
    cfg = make_config(short_loop, tmp_path / "out", viz={"rerun": "save"}, max_frames=5)
    seq = load_sequence(cfg)
    viewer = RerunLogger(cfg, seq)
    viewer.log_frame(None, FrameEstimate(3, float(seq.timestamps[3]), np.eye(4), skipped=True,
                                         note="skipped: black frame"))
    viewer.finish(RunResult(1, 0, 1, 0.1, _empty_trajectory(), [], False, ScaleReport()))
    chunks = list(RrdReader(str(tmp_path / "out" / "recording.rrd")).stream())
    texts = _rows(chunks, "/log", "TextLog:text")
    levels = _rows(chunks, "/log", "TextLog:level")
    assert [(r[0], r[2][0] if isinstance(r[2], list) else r[2]) for r in texts] == [(3, "frame 3 skipped: black frame")]
    assert (levels[0][2][0] if isinstance(levels[0][2], list) else levels[0][2]) == "WARN"


def _empty_trajectory():
    from windowvo.io.trajectory import Trajectory

    return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))


def test_jpeg_quality_is_validated(short_loop, tmp_path):
    with pytest.raises(WindowVOError, match="jpeg_quality"):
        make_config(short_loop, tmp_path / "out", viz={"jpeg_quality": 0})


def test_track_tails_start_where_each_track_was_first_seen_in_the_history():
    """A tail starts at the oldest frame of the history holding that track: checked against the
    definition, frame by frame, on random histories (tracks that start late, end early, or were never seen)."""
    rng = np.random.default_rng(3)
    history = []
    for _ in range(6):
        ids = np.sort(rng.choice(40, size=int(rng.integers(0, 25)), replace=False))
        history.append((ids, rng.uniform(0, 640, (len(ids), 2))))
    query = np.arange(45)  # 40..44 never seen
    got = tail_starts(history, query)
    for i, tid in enumerate(query):
        frames = [px[ids == tid][0] for ids, px in history if np.any(ids == tid)]
        if frames:
            assert np.array_equal(got[i], frames[0]), tid
        else:
            assert np.all(np.isnan(got[i])), tid
    assert tail_starts([], query).shape == (45, 2)
    assert tail_starts(history, query[:0]).shape == (0, 2)


def test_time_columns_are_rerun_s_own_conversion_of_the_seconds():
    """``time_columns`` hands rerun nanoseconds (its list-of-floats path converts one by one in Python): the same
    stamps to the nanosecond as rerun's conversion of the seconds, on the sequence clock and on Unix time."""
    import rerun as rr

    rng = np.random.default_rng(2)
    for epoch, base in ((False, 0.0), (True, 1.7e9)):
        for half in (0.0, 0.5e-9, 2.5e-9):  # ties of the rounding too
            times = [float(t) for t in base + half + np.cumsum(rng.uniform(0.0, 0.1, 300))]
            ours = time_columns(list(range(300)), times, epoch)[1].times
            theirs = rr.TimeColumn("time", timestamp=times) if epoch else rr.TimeColumn("time", duration=times)
            assert ours.equals(theirs.times), (epoch, half)
