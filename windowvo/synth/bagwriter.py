"""Write a native sequence folder as a ROS 1 or ROS 2 bag with ``rosbags`` (tests, bag benchmark).

``python -m windowvo.synth.bagwriter NATIVE_DIR OUT --format ros1|ros2|mcap`` converts a folder
on the command line (with ground truth as a PoseStamped topic; ``windowvo`` reads it with
``dataset: rosbag``).

The bag carries what a robot would record: camera images (raw or compressed), camera_info,
wheel odometry on its own clock (50 Hz, offset from the camera), ``/tf_static`` with the
camera mounted through an intermediate frame, and optionally ground truth.
"""

from __future__ import annotations

import argparse
import enum
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from windowvo.errors import WindowVOError, cli_error
from windowvo.geometry import R_BASE_CAM_FORWARD, inv_T, make_T, quat_from_R
from windowvo.io.odometry import read_odometry_csv
from windowvo.io.sequence import list_images, read_camera_yaml
from windowvo.io.trajectory import read_tum

EPOCH = 1_700_000_000.0  # the bag's clock: native time 0 is this many seconds since 1970
T_LINK_OPTICAL = make_T(R_BASE_CAM_FORWARD, np.zeros(3))  # ROS camera_link -> optical frame


class BagFormat(str, enum.Enum):
    """Bag formats of the command lines: a ROS 1 ``.bag`` file, or a ROS 2 bag folder (sqlite3 or mcap storage)."""

    ROS1 = "ros1"
    ROS2 = "ros2"
    MCAP = "mcap"

    @property
    def storage(self) -> str:
        return {BagFormat.ROS1: "ros1", BagFormat.ROS2: "sqlite3", BagFormat.MCAP: "mcap"}[self]


def bag_path_beside(native: Path, fmt: BagFormat) -> Path:
    """Where ``--bag`` puts the bag of the native folder ``DIR``: ``DIR.bag`` (ros1), ``DIR_ros2/`` or ``DIR_mcap/``."""
    native = Path(native)
    name = native.name + (".bag" if fmt is BagFormat.ROS1 else f"_{fmt.value}")
    return native.with_name(name)


@dataclass
class BagSpec:
    storage: str = "ros1"  # ros1 | sqlite3 | mcap
    image: str = "mono8"  # mono8 | mono16 | bgr8 | rgb8 | bayer_rggb8 | jpeg | png | or any encoding name
    image_topic: str = "/camera/image_raw"
    camera_info: bool = True
    camera_info_topic: str = "/camera/camera_info"
    distortion_model: str = "plumb_bob"
    distortion: list[float] | None = None  # default: the native camera.yaml coefficients
    odometry: str | None = "msg"  # msg | tf | None
    odometry_topic: str = "/odom"
    odometry_rate_hz: float = 50.0
    odometry_offset_s: float = 0.015
    tf_static: str | None = "chain"  # chain | broken | None
    groundtruth: str | None = None  # pose | odometry | tf
    groundtruth_topic: str = "/ground_truth/pose"
    extra_image_topic: str | None = None  # a second raw image topic (the same frames)
    record_latency_s: float = 0.004  # record time = header stamp + this
    zero_header_stamps: bool = False
    max_frames: int | None = None
    repeat: int = 1  # >1: drive the sequence forward, back, forward, ... (a bag `repeat` times as long)


def typestore(storage: str):
    if storage != "ros1":
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)
    # The Noetic store lacks tf2_msgs; register it from its message definition.
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def _stamp(ts, t: float):
    ns = round(t * 1e9)
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(ts, t: float, frame: str):
    H = ts.types["std_msgs/msg/Header"]
    if "seq" in H.__dataclass_fields__:
        return H(seq=0, stamp=_stamp(ts, t), frame_id=frame)
    return H(stamp=_stamp(ts, t), frame_id=frame)


def _pose(ts, T: np.ndarray):
    g = ts.types
    q = quat_from_R(T[:3, :3])
    return g["geometry_msgs/msg/Pose"](
        position=g["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=g["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def _transform(ts, t: float, parent: str, child: str, T_parent_child: np.ndarray):
    g = ts.types
    q = quat_from_R(T_parent_child[:3, :3])
    tr = g["geometry_msgs/msg/Transform"](
        translation=g["geometry_msgs/msg/Vector3"](x=float(T_parent_child[0, 3]), y=float(T_parent_child[1, 3]),
                                                   z=float(T_parent_child[2, 3])),
        rotation=g["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )
    return g["geometry_msgs/msg/TransformStamped"](header=_header(ts, t, parent), child_frame_id=child, transform=tr)


def _odometry_msg(ts, t: float, parent: str, child: str, T: np.ndarray):
    g = ts.types
    cov = np.zeros(36)
    return g["nav_msgs/msg/Odometry"](
        header=_header(ts, t, parent), child_frame_id=child,
        pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(ts, T), covariance=cov),
        twist=g["geometry_msgs/msg/TwistWithCovariance"](
            twist=g["geometry_msgs/msg/Twist"](linear=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                              angular=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
            covariance=cov),
    )


def _image_msg(ts, t: float, frame: str, img: np.ndarray, kind: str):
    g = ts.types
    hdr = _header(ts, t, frame)
    if kind in ("jpeg", "png"):
        ok, buf = cv2.imencode(".jpg" if kind == "jpeg" else ".png", img,
                               [cv2.IMWRITE_JPEG_QUALITY, 95] if kind == "jpeg" else [])
        assert ok
        return g["sensor_msgs/msg/CompressedImage"](header=hdr, format=kind, data=np.frombuffer(buf, np.uint8).copy())
    h, w = img.shape
    data: np.ndarray
    if kind == "mono16":
        data16 = img.astype(np.uint16) * 257
        data = data16.astype("<u2").view(np.uint8).ravel()
        step = 2 * w
    elif kind in ("bgr8", "rgb8"):
        data = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR).ravel()
        step = 3 * w
    elif kind.startswith("bayer_"):
        data = img.ravel()  # R = G = B: every Bayer site carries the grey value
        step = w
    else:  # mono8 or a deliberately unsupported encoding name
        data = img.ravel()
        step = w
    return g["sensor_msgs/msg/Image"](header=hdr, height=h, width=w, encoding=kind, is_bigendian=0, step=step,
                                       data=np.ascontiguousarray(data, dtype=np.uint8))


def _camera_info_msg(ts, t: float, frame: str, cam, model: str, dist: list[float]):
    g = ts.types
    CI = g["sensor_msgs/msg/CameraInfo"]
    upper = "K" in CI.__dataclass_fields__
    K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], float)
    P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0], float)
    R = np.eye(3).ravel()
    roi = g["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    mats = {"D": np.asarray(dist, float), "K": K, "R": R, "P": P}
    kw = {(k if upper else k.lower()): v for k, v in mats.items()}
    return CI(header=_header(ts, t, frame), height=cam.height, width=cam.width, distortion_model=model,
              binning_x=0, binning_y=0, roi=roi, **kw)


def _odometry_pose(odo, t: float) -> np.ndarray:
    """T_odom_base at t; linearly extrapolated (constant velocity) just outside the recorded span."""
    from windowvo.geometry import planar_T

    ts = odo.timestamps
    j = 0 if t < ts[0] else (len(ts) - 2 if t > ts[-1] else None)
    if j is None:
        return odo.pose_at(t)
    s = (t - ts[j]) / (ts[j + 1] - ts[j])
    return planar_T(*(float(a[j] + s * (a[j + 1] - a[j])) for a in (odo.x, odo.y, odo.yaw)))


@dataclass
class NativeRecording:
    """What a bag is written from: a native sequence's frames, wheel odometry and ground truth.

    With ``bag_times``/``src_times`` (ping-pong repeats) the bag's clock runs on while the robot
    drives the path back and forth: bag time ``bag_times[k]`` shows native time ``src_times[k]``.
    """

    cam: Any
    images: list[Path]
    times: np.ndarray
    odo: Any
    gt_times: np.ndarray
    gt_poses: np.ndarray
    has_gt: bool
    bag_times: np.ndarray | None = None
    src_times: np.ndarray | None = None

    def native_time(self, u: float) -> float:
        if self.bag_times is None or self.src_times is None:
            return u
        return float(np.interp(u, self.bag_times, self.src_times))


Event = tuple[float, str, str, object]  # (record time, topic, msgtype, message)


def read_native(native: Path, spec: BagSpec) -> NativeRecording:
    """The native folder's content, cut to ``spec.max_frames`` and repeated ``spec.repeat`` times."""
    cam = read_camera_yaml(native / "camera.yaml")
    images = list_images(native / "images")
    times = np.asarray([float(x) for x in (native / "times.txt").read_text().split()])
    if spec.max_frames is not None:
        images, times = images[: spec.max_frames], times[: spec.max_frames]
    odo = read_odometry_csv(native / "odometry.csv")
    gt = read_tum(native / "groundtruth.txt") if (native / "groundtruth.txt").is_file() else None
    gt_times, gt_poses = (gt.timestamps, gt.T_world_base) if gt is not None else (np.zeros(0), np.zeros((0, 4, 4)))
    rec = NativeRecording(cam, images, times, odo, gt_times, gt_poses, gt is not None)
    if spec.repeat > 1:
        _ping_pong(rec, spec.repeat, len(list_images(native / "images")))
    return rec


def _ping_pong(rec: NativeRecording, repeat: int, n_native: int) -> None:
    """Forward, then the same path reversed (the robot backs up), and so on. Images, odometry and
    ground truth all follow the same bag-time -> native-time map, so they agree."""
    n = len(rec.images)
    order: list[int] = []
    for k in range(repeat):
        order += list(range(n)) if k % 2 == 0 else list(range(n - 2, 0, -1))
    dt = float(np.median(np.diff(rec.times)))
    rec.bag_times = rec.times[0] + dt * np.arange(len(order))
    rec.src_times = rec.times[order]
    if rec.has_gt and len(rec.gt_times) == n_native:
        rec.gt_times, rec.gt_poses = rec.bag_times, rec.gt_poses[order]
    rec.images, rec.times = [rec.images[i] for i in order], rec.bag_times


def _static_events(ts, rec: NativeRecording, spec: BagSpec) -> list[Event]:
    """/tf_static (latched, at the start) and camera_info at 2 Hz."""
    events: list[Event] = []
    t_first = EPOCH + rec.times[0]
    lat = spec.record_latency_s
    if spec.tf_static is not None:
        T_base_link = rec.cam.T_base_cam @ inv_T(T_LINK_OPTICAL)  # base_link -> camera_link
        tfs = [_transform(ts, t_first, "base_link", "camera_link", T_base_link)]
        if spec.tf_static == "chain":
            tfs.append(_transform(ts, t_first, "camera_link", "camera_optical_frame", T_LINK_OPTICAL))
        events.append((t_first - 0.01, "/tf_static", "tf2_msgs/msg/TFMessage",
                       ts.types["tf2_msgs/msg/TFMessage"](transforms=tfs)))
    if spec.camera_info:
        dist = list(rec.cam.distortion) if spec.distortion is None else list(spec.distortion)
        for k, t in enumerate(rec.times):
            if k % 10 == 0:  # camera_info at 2 Hz is plenty
                events.append((EPOCH + t + lat, spec.camera_info_topic, "sensor_msgs/msg/CameraInfo",
                               _camera_info_msg(ts, EPOCH + t, "camera_optical_frame", rec.cam,
                                                spec.distortion_model, dist)))
    return events


def _image_events(rec: NativeRecording, spec: BagSpec) -> list[Event]:
    """One event per frame; unreadable images (a corrupt PNG) are left out, like a dropped frame."""
    events: list[Event] = []
    lat = spec.record_latency_s
    for t, p in zip(rec.times, rec.images):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            continue
        kind = spec.image
        msgtype = "sensor_msgs/msg/CompressedImage" if kind in ("jpeg", "png") else "sensor_msgs/msg/Image"
        stamp = 0.0 if spec.zero_header_stamps else EPOCH + t
        events.append((EPOCH + t + lat, spec.image_topic, msgtype, (_image_msg, stamp, img, kind)))
        if spec.extra_image_topic:
            events.append((EPOCH + t + lat, spec.extra_image_topic, "sensor_msgs/msg/Image",
                           (_image_msg, stamp, img, "mono8")))
    return events


def _odometry_events(ts, rec: NativeRecording, spec: BagSpec) -> list[Event]:
    """The wheel clock: rate_hz samples at camera time + offset (mod the period), from just before the first
    frame (the robot's odometry runs before the camera starts) to just after the last one."""
    events: list[Event] = []
    if spec.odometry is None:
        return events
    lat = spec.record_latency_s
    times = rec.times
    dt = 1.0 / spec.odometry_rate_hz
    k0 = int(np.floor((times[0] - spec.odometry_offset_s) / dt))
    t_odo = spec.odometry_offset_s + dt * np.arange(k0, k0 + int((times[-1] - times[0]) / dt) + 3)
    for t in t_odo:
        T = _odometry_pose(rec.odo, float(rec.native_time(t)))
        if spec.odometry == "msg":
            events.append((EPOCH + t + lat, spec.odometry_topic, "nav_msgs/msg/Odometry",
                           _odometry_msg(ts, EPOCH + t, "odom", "base_link", T)))
        else:
            events.append((EPOCH + t + lat, "/tf", "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](
                transforms=[_transform(ts, EPOCH + t, "odom", "base_link", T)])))
    return events


def _groundtruth_events(ts, rec: NativeRecording, spec: BagSpec) -> list[Event]:
    events: list[Event] = []
    if spec.groundtruth is None or not rec.has_gt:
        return events
    lat = spec.record_latency_s
    for t, T in zip(rec.gt_times, rec.gt_poses):
        if t > rec.times[-1] + 1e-9:
            break
        if spec.groundtruth == "pose":
            msg = ts.types["geometry_msgs/msg/PoseStamped"](header=_header(ts, EPOCH + t, "world"), pose=_pose(ts, T))
            events.append((EPOCH + t + lat, spec.groundtruth_topic, "geometry_msgs/msg/PoseStamped", msg))
        elif spec.groundtruth == "odometry":
            events.append((EPOCH + t + lat, spec.groundtruth_topic, "nav_msgs/msg/Odometry",
                           _odometry_msg(ts, EPOCH + t, "world", "base_link_gt", T)))
        else:
            events.append((EPOCH + t + lat, "/tf", "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](
                transforms=[_transform(ts, EPOCH + t, "world", "base_gt", T)])))
    return events


def _write_events(ts, out: Path, storage: str, events: list[Event]) -> None:
    serialize = ts.serialize_ros1 if storage == "ros1" else ts.serialize_cdr
    if storage == "ros1":
        writer: Writer1 | Writer2 = Writer1(out)
    else:
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(out, version=9, storage_plugin=plugin)
    conns: dict[str, Any] = {}
    with writer:
        for t_rec, topic, msgtype, msg in events:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            if isinstance(msg, tuple):  # images are built one at a time to keep memory small
                make, stamp, img, kind = msg
                msg = make(ts, stamp, "camera_optical_frame", img, kind)
            writer.write(conns[topic], round(t_rec * 1e9), serialize(msg, msgtype))


def write_bag(native: Path, out: Path, spec: BagSpec) -> Path:
    """Write the native sequence ``native`` as a bag at ``out`` (a ``.bag`` file or a ROS 2 folder)."""
    ts = typestore(spec.storage)
    rec = read_native(Path(native), spec)
    events = _static_events(ts, rec, spec)
    events += _image_events(rec, spec)
    events += _odometry_events(ts, rec, spec)
    events += _groundtruth_events(ts, rec, spec)
    events.sort(key=lambda e: e[0])  # stable: equal record times keep the order above
    _write_events(ts, Path(out), spec.storage, events)
    return out


def bag_spec_for(fmt: BagFormat) -> BagSpec:
    """The bag the command lines write: mono8 images, camera_info, /tf_static, /odom and ground truth."""
    return BagSpec(storage=BagFormat(fmt).storage, groundtruth="pose")


def check_bag_target(out: Path) -> None:
    if Path(out).exists():
        raise WindowVOError(f"bag output {out} exists already (remove it or choose another name)")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (not argparse's usage block)
        sys.exit(cli_error(message, "windowvo.synth.bagwriter"))


def main(argv=None) -> int:
    p = _Parser(prog="python -m windowvo.synth.bagwriter",
                description="Write a native sequence folder (images/, times.txt, camera.yaml, odometry.csv, "
                            "groundtruth.txt) as a ROS bag that dataset: rosbag reads.")
    p.add_argument("native", type=Path, help="native sequence folder")
    p.add_argument("out", type=Path, help="bag to write: a .bag file (ros1) or a new folder (ros2, mcap)")
    p.add_argument("--format", choices=[f.value for f in BagFormat], default=BagFormat.ROS2.value,
                   help="ros1 (.bag file), ros2 (sqlite3 folder) or mcap (ROS 2 folder with an .mcap file)")
    a = p.parse_args(argv)
    try:
        for name in ("camera.yaml", "times.txt", "odometry.csv", "images"):
            if not (a.native / name).exists():
                raise WindowVOError(f"{a.native} is not a native sequence folder (no {name})")
        check_bag_target(a.out)
        write_bag(a.native, a.out, bag_spec_for(BagFormat(a.format)))
    except (WindowVOError, ValueError, OSError) as err:
        return cli_error(err, "windowvo.synth.bagwriter")
    print(f"wrote {a.format} bag {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
