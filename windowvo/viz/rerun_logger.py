"""Streams a run to Rerun (live viewer, web viewer, or an .rrd recording).

Entity layout (world is z up, like the robot base):

* ``world/estimate``          estimated keyframe path (refreshed every 10 keyframes), current pose, and
  the final per-frame trajectory
* ``world/estimate/base/cam`` camera frustum: transform plus pinhole, with the image
  and the tracked features (coloured by age, RANSAC outliers red, short tails as arrows)
* ``world/window``            the window's keyframe poses (points)
* ``world/landmarks``         the window's landmarks
* ``world/wheel_odometry``    wheel odometry alone; ``world/groundtruth`` when present
* ``plots/*``                 tracked features, inlier ratio, parallax, reprojection RMS, back-end ms

Timelines: ``frame`` (index) and ``time`` (seconds, the sequence clock).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..config import Config, RerunMode
from ..geometry import quat_from_R
from ..types import Frame, FrameEstimate, FrontendOutput

if TYPE_CHECKING:  # pragma: no cover
    from ..io.sequence import Sequence
    from ..pipeline import RunResult

log = logging.getLogger(__name__)


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="3D", origin="world"),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin="world/estimate/base/cam"),
                rrb.TimeSeriesView(name="plots", origin="plots"),
                row_shares=[3, 2],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def age_colors(ages: np.ndarray) -> np.ndarray:
    """Young tracks blue, old tracks green-yellow."""
    a = np.clip(ages / 30.0, 0.0, 1.0)[:, None]
    young = np.array([[60, 120, 255]])
    old = np.array([[230, 230, 40]])
    return (young * (1 - a) + old * a).astype(np.uint8)


def _transform(T: np.ndarray) -> rr.Transform3D:
    q = quat_from_R(T[:3, :3])
    return rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=q))


class RerunLogger:
    def __init__(self, cfg: Config, seq: Sequence, recording_path=None):
        self.cfg = cfg
        self.seq = seq
        self.rec = rr.RecordingStream("windowvo", make_default=False)
        mode = cfg.viz.rerun
        self.path = None
        if mode is RerunMode.SAVE:
            self.path = recording_path or (cfg.output / "recording.rrd")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self.path), default_blueprint=blueprint())
        elif mode is RerunMode.SPAWN:
            self.rec.spawn(default_blueprint=blueprint())
        elif mode is RerunMode.CONNECT:
            self.rec.connect_grpc(cfg.viz.connect_url, default_blueprint=blueprint())
        elif mode is RerunMode.SERVE:
            uri = self.rec.serve_grpc(default_blueprint=blueprint())
            rr.serve_web_viewer(connect_to=uri, open_browser=False)
            log.info("Rerun web viewer serving %s", uri)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        cam = seq.camera
        self.rec.log("world/estimate/base/cam", rr.Transform3D(
            translation=cam.T_base_cam[:3, 3], mat3x3=cam.T_base_cam[:3, :3]), static=True)
        self.rec.log("world/estimate/base/cam", rr.Pinhole(
            image_from_camera=cam.K, width=cam.width, height=cam.height,
            camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3), static=True)
        self._log_reference_trajectories()
        self.est_positions: list[np.ndarray] = []
        # Pixels of the tracks over the last few frames, for the tails: (ids, pixels) per frame.
        self._tail_history: list[tuple[np.ndarray, np.ndarray]] = []

    def _log_reference_trajectories(self) -> None:
        seq = self.seq
        ts = seq.timestamps
        if seq.groundtruth is not None:
            gt = seq.groundtruth.anchored()
            self.rec.log("world/groundtruth", rr.LineStrips3D([gt.positions], colors=[[160, 160, 160]], radii=0.01),
                         static=True)
        if seq.odometry is not None:
            odo = seq.odometry
            t0 = float(ts[0])
            pts = np.stack([odo.delta(t0, float(t))[:3, 3] for t in ts[:: max(1, len(ts) // 500)]])
            self.rec.log("world/wheel_odometry", rr.LineStrips3D([pts], colors=[[255, 150, 40]], radii=0.01),
                         static=True)

    def log_frame(self, frame: Frame, est: FrameEstimate) -> None:
        fo, bo = est.frontend, est.backend
        if fo is None:
            return
        rec = self.rec
        tail = self.cfg.viz.track_tail
        if tail > 1:
            self._tail_history.append((fo.track_ids, fo.pixels))
            del self._tail_history[:-tail]
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("time", duration=float(frame.timestamp))
        cam_path = "world/estimate/base/cam"
        if frame.index % self.cfg.viz.image_every == 0:
            self._log_camera(frame, fo, cam_path)
        rec.log("plots/tracked_features", rr.Scalars(float(len(fo.track_ids))))
        rec.log("plots/inlier_ratio", rr.Scalars(float(fo.inlier_ratio)))
        rec.log("plots/parallax_px", rr.Scalars(float(fo.parallax_px)))
        rec.log("plots/frontend_ms", rr.Scalars(float(fo.frontend_ms)))
        if bo is not None:
            T = bo.T_world_base
            rec.log("world/estimate/base", _transform(T))
            self.est_positions.append(T[:3, 3].copy())
            if len(self.est_positions) % 10 == 1:
                # the whole keyframe path, every 10 keyframes (keeps the cost per frame flat)
                rec.log("world/estimate/keyframes", rr.LineStrips3D([np.asarray(self.est_positions)],
                                                                    colors=[[40, 200, 90]], radii=0.015))
            win = np.asarray([P[:3, 3] for P in bo.keyframe_poses.values()])
            rec.log("world/window", rr.Points3D(win, colors=[[40, 200, 90]], radii=0.05))
            if len(bo.p_world_landmarks):
                rec.log("world/landmarks", rr.Points3D(bo.p_world_landmarks, colors=[[220, 220, 255]], radii=0.02))
            if np.isfinite(bo.reprojection_rms_px):
                rec.log("plots/reprojection_rms_px", rr.Scalars(float(bo.reprojection_rms_px)))
            rec.log("plots/backend_ms", rr.Scalars(float(bo.backend_ms)))
            rec.log("log", rr.TextLog(f"keyframe {fo.frame_index}: {fo.keyframe_reason.value}, gate {fo.gate.value}, "
                                      f"backend {bo.status.value}"))

    def _tail_starts(self, ids: np.ndarray) -> np.ndarray:
        """Where each track was at the oldest frame of the tail history it appears in, (N, 2)."""
        start = np.full((len(ids), 2), np.nan)
        for h_ids, h_px in reversed(self._tail_history):
            _, a, b = np.intersect1d(ids, h_ids, return_indices=True)
            start[a] = h_px[b]
        return start

    def _log_camera(self, frame: Frame, fo: FrontendOutput, cam_path: str) -> None:
        rec = self.rec
        rec.log(f"{cam_path}/image", rr.Image(frame.image))
        rec.log(f"{cam_path}/tracks", rr.Points2D(fo.pixels, colors=age_colors(fo.track_ages), radii=2.0))
        if len(fo.outlier_pixels):
            rec.log(f"{cam_path}/outliers", rr.Points2D(fo.outlier_pixels, colors=[[255, 40, 40]], radii=3.0))
        else:
            rec.log(f"{cam_path}/outliers", rr.Clear(recursive=False))
        tail = self.cfg.viz.track_tail
        if tail > 1 and len(fo.track_ids):
            # Track tails as arrows from where each track was `tail` frames ago to where it is.
            start = self._tail_starts(fo.track_ids)
            ok = np.all(np.isfinite(start), axis=1)
            rec.log(f"{cam_path}/tails", rr.Arrows2D(origins=start[ok], vectors=fo.pixels[ok] - start[ok],
                                                     colors=[[90, 200, 255]], radii=0.6))

    def finish(self, result: RunResult, report=None) -> None:
        """Log the final trajectory (one pose per frame), the same as trajectory.txt."""
        traj = result.trajectory
        if len(traj) and result.last_frame_index >= 0:
            last_frame = result.last_frame_index
            self.rec.set_time("frame", sequence=last_frame)
            self.rec.set_time("time", duration=float(traj.timestamps[-1]))
            self.rec.log("world/estimate/final", rr.LineStrips3D([traj.positions], colors=[[40, 200, 90]], radii=0.02))
            self.rec.log("world/estimate/base", _transform(traj.T_world_base[-1]))
        self.rec.flush()
        if self.path is not None:
            self.rec.disconnect()
