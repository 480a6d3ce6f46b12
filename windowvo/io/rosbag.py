"""ROS bags as input (``dataset: rosbag``), read with ``rosbags``: no ROS installation needed.

Reads ROS 1 ``.bag`` files and ROS 2 bags (a folder with ``metadata.yaml``, or a bare
``.db3`` / ``.mcap`` file). What becomes of each message type:

* images: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8) and
  ``sensor_msgs/CompressedImage`` (jpeg, png), converted to grayscale uint8. Frames are
  decoded on demand from a forward iterator over the image topic (:class:`BagFrameSource`);
  only their timestamps (header stamps, or the record time when a stamp is zero) are read
  upfront, so memory stays flat for a bag of any size.
* intrinsics: ``sensor_msgs/CameraInfo`` (``plumb_bob`` and ``rational_polynomial`` with
  k4..k6 = 0 become radtan, ``equidistant`` stays equidistant), unless the config has a
  ``camera:`` section, which wins.
* ``T_base_cam``: the chain of ``/tf_static`` transforms from the base frame to the camera
  (optical) frame, in either direction, unless the config gives ``camera.T_base_cam``.
* wheel odometry: ``nav_msgs/Odometry`` (planar x, y, yaw of the pose) or the
  ``odom -> base`` transform on ``/tf``, on its own clock.
* ground truth (optional): ``geometry_msgs/PoseStamped``, ``nav_msgs/Odometry`` or a pair of
  frames on ``/tf``: the pose of the base in a world frame, interpolated at the image times
  and anchored like every other loader (world = base at the first frame).

Topics and frames are auto-detected when unambiguous and otherwise named in the config's
``rosbag:`` section. A bag that was cut off (or an MCAP/ROS 1 bag without its index) is
scanned sequentially and the frames before the damage are used, with a warning.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ..camera import CameraModel, DistortionModel
from ..config import CameraConfig, Config, OdometrySourceKind, RosbagConfig
from ..errors import CalibrationError, FrameError, SequenceError
from ..geometry import R_from_quat, inv_T, make_T
from .bagsalvage import Damage, SalvageConnection, scan_mcap, scan_ros1, scan_sqlite
from .common import T_BASE_CAM_FORWARD, anchor, interp_poses
from .odometry import WheelOdometry
from .sequence import StreamedSequence, check_odometry_overlap
from .trajectory import Trajectory

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
GROUNDTRUTH_TYPES = (POSE_STAMPED, ODOMETRY)
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
# A topic whose name says it is ground truth (used to tell it apart from wheel odometry).
GROUNDTRUTH_NAME = re.compile(r"ground_?truth|(^|[/_])gt($|[/_])|mocap|vicon|optitrack", re.IGNORECASE)

BAYER_CODES = {
    "bayer_rggb8": cv2.COLOR_BayerRGGB2GRAY,
    "bayer_bggr8": cv2.COLOR_BayerBGGR2GRAY,
    "bayer_gbrg8": cv2.COLOR_BayerGBRG2GRAY,
    "bayer_grbg8": cv2.COLOR_BayerGRBG2GRAY,
}
COLOR_CODES = {  # encoding -> (channels, conversion to grey)
    "rgb8": (3, cv2.COLOR_RGB2GRAY),
    "bgr8": (3, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY),
    "bgra8": (4, cv2.COLOR_BGRA2GRAY),
}
MONO8 = ("mono8", "8uc1")
MONO16 = ("mono16", "16uc1")
SUPPORTED_ENCODINGS = ("mono8", "mono16", *COLOR_CODES, *BAYER_CODES)


class BagDamage(Exception):
    """Reading stopped at a damaged part of the bag (internal; callers turn it into a warning)."""


# ---------------------------------------------------------------------------- reading


@dataclass
class BagTopic:
    name: str
    msgtype: str
    count: int
    ids: list = field(default_factory=list)  # connections (indexed bag) or connection ids (salvage)


def _norm_type(t: str) -> str:
    parts = t.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else t


def _norm_frame(f: str) -> str:
    return f.lstrip("/")


class BagReader:
    """Uniform access to a bag: ``rosbags``' indexed readers, or a sequential scan of a damaged file.

    ``topics`` maps topic name to :class:`BagTopic`; ``messages`` yields ``(topic, record time ns,
    raw bytes)`` in record-time order and raises :class:`BagDamage` where the data is unreadable;
    ``damage`` describes why the bag had to be salvaged (None for a healthy bag).
    """

    def __init__(self, path: Path, salvage: str | None = None):
        self.path = Path(path)
        self.damage: str | None = None
        self.topics: dict[str, BagTopic] = {}
        self.start_ns = 0
        self.end_ns = 0
        self.is2 = not (self.path.is_file() and self.path.suffix == ".bag")
        self._any: Any = None
        self._salvage: list[SalvageConnection] | None = None
        self._typestore: Typestore | None = None
        if not self.path.exists():
            raise SequenceError(f"bag not found: {self.path}")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise SequenceError(f"not a ROS 2 bag (no metadata.yaml in the folder): {self.path}")
        if self.path.is_file() and self.path.suffix not in (".bag", ".db3", ".mcap"):
            raise SequenceError(f"not a bag (expected .bag, .db3, .mcap or a ROS 2 bag folder): {self.path}")
        if salvage is not None:  # the reason the index cannot be trusted
            self._open_salvage(salvage)
            return
        try:
            self._open_indexed()
        except Exception as err:  # rosbags raises many types on damaged input
            reason = " ".join(str(a) for a in getattr(err, "args", ())) or type(err).__name__
            self._open_salvage(reason)

    # -- healthy bags
    def _open_indexed(self) -> None:
        from rosbags.highlevel import AnyReader

        reader = AnyReader([self.path])
        reader.open()
        self._any = reader
        self.start_ns, self.end_ns = reader.start_time, reader.end_time
        for name, info in reader.topics.items():
            msgtype = _norm_type(info.msgtype or "")
            self.topics[name] = BagTopic(name, msgtype, int(info.msgcount), list(info.connections))

    # -- damaged bags
    def _storage_file(self) -> tuple[Path, str]:
        if self.path.is_file():
            return self.path, self.path.suffix
        for suffix in (".mcap", ".db3"):
            files = sorted(self.path.glob(f"*{suffix}"))
            if files:
                return files[0], suffix
        raise SequenceError(f"no .db3 or .mcap file in the bag folder {self.path}")

    def _scan(self) -> Iterator:
        f, suffix = self._storage_file()
        return {".bag": scan_ros1, ".mcap": scan_mcap}.get(suffix, scan_sqlite)(f)

    def _open_salvage(self, reason: str) -> None:
        conns: dict[int, SalvageConnection] = {}
        counts: Counter = Counter()
        t_min, t_max = None, None
        where = "the end of the file"
        try:
            for rec in self._scan():
                if isinstance(rec, SalvageConnection):
                    conns[rec.cid] = rec
                elif rec.cid in conns:
                    counts[rec.cid] += 1
                    t_min = rec.time_ns if t_min is None else min(t_min, rec.time_ns)
                    t_max = rec.time_ns if t_max is None else max(t_max, rec.time_ns)
        except Damage as err:
            where = str(err)
        except OSError as err:
            raise SequenceError(f"cannot read bag {self.path}: {err}") from None
        if not counts:
            raise SequenceError(f"bag {self.path} is damaged and holds no readable message ({reason}; {where})")
        self.damage = f"{reason}; read sequentially until: {where}"
        self._salvage = list(conns.values())
        self.start_ns, self.end_ns = int(t_min or 0), int(t_max or 0) + 1
        for c in conns.values():
            name = c.topic
            t = self.topics.setdefault(name, BagTopic(name, _norm_type(c.msgtype), 0, []))
            t.count += counts[c.cid]
            t.ids.append(c.cid)
        self._typestore = self._salvage_typestore()

    def _salvage_typestore(self) -> Typestore:
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_HUMBLE if self.is2 else Stores.ROS1_NOETIC)
        types: dict = {}
        for c in self._salvage or []:
            try:
                if c.msgdef_format == "msg" and c.msgdef:
                    types.update(get_types_from_msg(c.msgdef, _norm_type(c.msgtype)))
                elif c.msgdef_format == "idl" and c.msgdef:
                    types.update(get_types_from_idl(c.msgdef))
            except Exception as err:  # a definition rosbags cannot parse: fall back to the built-in types
                log.debug("message definition of %s not usable: %s", c.topic, err)
        if types:
            store.register(types)
        return store

    # -- access
    def messages(self, topics: list[str], start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[tuple[str, int, bytes]]:
        wanted = [self.topics[t] for t in topics if t in self.topics]
        if self._any is not None:
            conns = [c for t in wanted for c in t.ids]
            if not conns:
                return
            try:
                for conn, t_ns, raw in self._any.messages(connections=conns, start=start_ns, stop=stop_ns):
                    yield conn.topic, int(t_ns), bytes(raw)
            except Exception as err:  # damaged data behind an intact index
                raise BagDamage(f"{type(err).__name__}: {err}") from None
            return
        by_id = {cid: t.name for t in wanted for cid in t.ids}
        try:
            for rec in self._scan():
                if isinstance(rec, SalvageConnection) or rec.cid not in by_id:
                    continue
                if (start_ns is not None and rec.time_ns < start_ns) or (stop_ns is not None and rec.time_ns >= stop_ns):
                    continue
                yield by_id[rec.cid], rec.time_ns, rec.data
        except Damage:
            return  # already reported when the bag was opened

    def deserialize(self, raw: bytes, msgtype: str):
        try:
            if self._any is not None:
                return self._any.deserialize(raw, msgtype)
            store = self._typestore
            assert store is not None
            return store.deserialize_cdr(raw, msgtype) if self.is2 else store.deserialize_ros1(raw, msgtype)
        except Exception as err:
            raise BagDamage(f"cannot deserialise a {msgtype} message: {err}") from None

    def close(self) -> None:
        if self._any is not None:
            try:
                self._any.close()
            finally:
                self._any = None

    def describe_topics(self) -> str:
        return ", ".join(f"{t.name} ({t.msgtype}, {t.count})" for t in sorted(self.topics.values(), key=lambda t: t.name))


def _stamp_ns(header, t_rec: int) -> int:
    s = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return s if s > 0 else t_rec


# ---------------------------------------------------------------------------- images


@dataclass
class ImageDecoder:
    """Turns Image / CompressedImage messages into grayscale uint8."""

    topic: str
    mono16_shift: int | None = None  # set from the first mono16 frame (its highest bit in use)

    def decode(self, msg, msgtype: str) -> np.ndarray:
        if msgtype == COMPRESSED_IMAGE:
            fmt = str(msg.format).lower()
            if "compresseddepth" in fmt:
                raise SequenceError(f"image topic {self.topic}: compressed depth images are not supported")
            img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise FrameError(f"compressed image (format '{msg.format}') cannot be decoded")
            return img
        enc = str(msg.encoding).lower()
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        data = np.asarray(msg.data, dtype=np.uint8)
        if h <= 0 or w <= 0 or data.size < h * step:
            raise FrameError(f"image data ({data.size} bytes) shorter than height x step ({h} x {step})")
        rows = data[: h * step].reshape(h, step)
        if enc in MONO8:
            return np.ascontiguousarray(rows[:, :w])
        if enc in BAYER_CODES:
            return cv2.cvtColor(np.ascontiguousarray(rows[:, :w]), BAYER_CODES[enc])
        if enc in COLOR_CODES:
            c, code = COLOR_CODES[enc]
            return cv2.cvtColor(np.ascontiguousarray(rows[:, : c * w]).reshape(h, w, c), code)
        if enc in MONO16:
            px = np.ascontiguousarray(rows[:, : 2 * w]).view(">u2" if msg.is_bigendian else "<u2").reshape(h, w)
            if self.mono16_shift is None:  # 10-, 12- or 16-bit data: keep the top 8 bits in use
                self.mono16_shift = max(8, int(px.max()).bit_length()) - 8
            return np.clip(px >> self.mono16_shift, 0, 255).astype(np.uint8)
        raise SequenceError(
            f"image topic {self.topic}: encoding '{msg.encoding}' is not supported "
            f"(supported: {', '.join(SUPPORTED_ENCODINGS)}, or CompressedImage jpeg/png)")


class BagFrameSource:
    """Frame i of the sequence decoded on demand from a forward iterator over the image topic.

    ``ordinals[i]`` is the position of frame i among the topic's messages in the time
    window; reading an earlier frame than the last one restarts the reader.
    """

    def __init__(self, path: Path, topic: str, msgtype: str, ordinals: np.ndarray, start_ns: int | None,
                 stop_ns: int | None, decoder: ImageDecoder, salvage: str | None = None):
        self.path, self.topic, self.msgtype = path, topic, msgtype
        self.salvage = salvage
        self.ordinals = ordinals
        self.start_ns, self.stop_ns = start_ns, stop_ns
        self.decoder = decoder
        self._reader: BagReader | None = None
        self._it: Iterator | None = None
        self._next = 0  # ordinal of the message the iterator yields next
        self.restarts = 0

    def _restart(self) -> None:
        self.close()
        self._reader = BagReader(self.path, salvage=self.salvage)
        self._it = self._reader.messages([self.topic], self.start_ns, self.stop_ns)
        self._next = 0
        self.restarts += 1

    def read(self, i: int) -> np.ndarray:
        target = int(self.ordinals[i])
        if self._it is None or target < self._next:
            self._restart()
        assert self._it is not None and self._reader is not None
        try:
            while True:
                _topic, _t, raw = next(self._it)
                self._next += 1
                if self._next - 1 == target:
                    break
        except StopIteration:
            self._it = None
            raise FrameError(f"frame {i}: the bag ended before this frame") from None
        except BagDamage as err:
            self._it = None
            raise FrameError(f"frame {i}: damaged bag data ({err})") from None
        try:
            msg = self._reader.deserialize(raw, self.msgtype)
        except BagDamage as err:
            raise FrameError(f"frame {i}: {err}") from None
        return self.decoder.decode(msg, self.msgtype)

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
        self._reader, self._it = None, None


# ---------------------------------------------------------------------------- topic selection


@dataclass
class Choice:
    """What the loader would use for one role, and why (or what is wrong)."""

    role: str
    topic: str | None = None
    reason: str = ""
    problem: str | None = None  # set when the choice is ambiguous or the named topic is missing

    def line(self) -> str:
        if self.problem:
            return f"{self.role}: ? ({self.problem})"
        return f"{self.role}: {self.topic or 'none'} ({self.reason})"


def _of_type(bag: BagReader, types: tuple[str, ...]) -> list[str]:
    return sorted(t.name for t in bag.topics.values() if t.msgtype in types)


def _named(bag: BagReader, role: str, key: str, topic: str, types: tuple[str, ...]) -> Choice:
    t = bag.topics.get(topic)
    if t is None:
        return Choice(role, problem=f"rosbag.{key} '{topic}' is not in the bag; it has: {bag.describe_topics()}")
    if t.msgtype not in types:
        return Choice(role, problem=f"rosbag.{key} '{topic}' is a {t.msgtype}, expected {' or '.join(types)}")
    return Choice(role, topic, f"rosbag.{key}")


def _namespace(topic: str) -> str:
    parts = topic.rstrip("/").split("/")
    if parts and parts[-1] == "compressed":
        parts = parts[:-1]
    return "/".join(parts[:-1])


@dataclass
class Selection:
    image: Choice
    camera_info: Choice
    groundtruth: Choice
    odometry: Choice
    odometry_source: OdometrySourceKind  # MESSAGE, TF or NONE once resolved (TF may still find nothing)


def _image_choice(bag: BagReader, rc: RosbagConfig) -> Choice:
    """The image topic: named, or the only one."""
    if rc.image_topic:
        image = _named(bag, "images", "image_topic", rc.image_topic, IMAGE_TYPES)
    else:
        cands = _of_type(bag, IMAGE_TYPES)
        if len(cands) == 1:
            image = Choice("images", cands[0], "the only image topic")
        elif not cands:
            image = Choice("images", problem="no sensor_msgs/Image or CompressedImage topic in the bag; it has: "
                           + bag.describe_topics())
        else:
            image = Choice("images", problem=f"several image topics ({', '.join(cands)}): set rosbag.image_topic")
    return image


def _camera_info_choice(bag: BagReader, rc: RosbagConfig, image: Choice) -> Choice:
    """The CameraInfo topic: named, the only one, or the one beside the image topic."""
    if rc.camera_info_topic:
        info = _named(bag, "camera_info", "camera_info_topic", rc.camera_info_topic, (CAMERA_INFO,))
    else:
        cands = _of_type(bag, (CAMERA_INFO,))
        same_ns = [c for c in cands if image.topic and _namespace(c) == _namespace(image.topic)]
        if len(cands) == 1:
            info = Choice("camera_info", cands[0], "the only CameraInfo topic")
        elif not cands:
            info = Choice("camera_info", None, "no CameraInfo topic: intrinsics from the config's camera section")
        elif len(same_ns) == 1:
            info = Choice("camera_info", same_ns[0], "the CameraInfo topic beside the image topic")
        else:
            info = Choice("camera_info", problem=f"several CameraInfo topics ({', '.join(cands)}): "
                          "set rosbag.camera_info_topic")
    return info


def _groundtruth_choice(bag: BagReader, rc: RosbagConfig) -> Choice:
    """Ground truth: a named topic, a /tf frame pair, or the only pose topic named like ground truth."""
    if rc.groundtruth_topic:
        gt = _named(bag, "ground truth", "groundtruth_topic", rc.groundtruth_topic, GROUNDTRUTH_TYPES)
    elif rc.groundtruth_parent_frame:
        if TF_TOPIC not in bag.topics:
            gt = Choice("ground truth", problem="rosbag.groundtruth_parent/child_frame set but the bag has no /tf")
        else:
            gt = Choice("ground truth", TF_TOPIC,
                        f"/tf {rc.groundtruth_parent_frame} -> {rc.groundtruth_child_frame} (rosbag.groundtruth_*_frame)")
    else:
        cands = [c for c in _of_type(bag, GROUNDTRUTH_TYPES) if GROUNDTRUTH_NAME.search(c)]
        if len(cands) == 1:
            gt = Choice("ground truth", cands[0], "the only pose topic named like ground truth")
        elif not cands:
            gt = Choice("ground truth", None, "no PoseStamped/Odometry topic named like ground truth")
        else:
            gt = Choice("ground truth", None, f"several candidates ({', '.join(cands)}); set rosbag.groundtruth_topic "
                        "to use one")
    return gt


def _odometry_choice(bag: BagReader, rc: RosbagConfig, gt: Choice) -> tuple[Choice, OdometrySourceKind]:
    """Wheel odometry (topic or /tf) and the source it resolves to."""
    src = rc.odometry_source
    odo_cands = [c for c in _of_type(bag, (ODOMETRY,)) if c != gt.topic and not GROUNDTRUTH_NAME.search(c)]
    if src is OdometrySourceKind.NONE:
        odo = Choice("odometry", None, "rosbag.odometry_source: none")
        resolved = OdometrySourceKind.NONE
    elif rc.odometry_topic:
        odo = _named(bag, "odometry", "odometry_topic", rc.odometry_topic, (ODOMETRY,))
        resolved = OdometrySourceKind.MESSAGE
    elif src is OdometrySourceKind.TF:
        if TF_TOPIC in bag.topics:
            odo = Choice("odometry", TF_TOPIC, f"/tf {rc.odom_frame} -> base (rosbag.odometry_source: tf)")
        else:
            odo = Choice("odometry", problem="rosbag.odometry_source is tf but the bag has no /tf topic")
        resolved = OdometrySourceKind.TF
    elif len(odo_cands) == 1:
        odo = Choice("odometry", odo_cands[0], "the only nav_msgs/Odometry topic")
        resolved = OdometrySourceKind.MESSAGE
    elif len(odo_cands) > 1:
        odo = Choice("odometry", problem=f"several Odometry topics ({', '.join(odo_cands)}): set rosbag.odometry_topic "
                     "(or rosbag.odometry_source: none)")
        resolved = OdometrySourceKind.MESSAGE
    elif src is OdometrySourceKind.MESSAGE:
        odo = Choice("odometry", problem="rosbag.odometry_source is message but the bag has no nav_msgs/Odometry topic")
        resolved = OdometrySourceKind.MESSAGE
    elif TF_TOPIC in bag.topics:
        odo = Choice("odometry", TF_TOPIC, f"no Odometry topic: /tf {rc.odom_frame} -> base, if present")
        resolved = OdometrySourceKind.TF
    else:
        odo = Choice("odometry", None, "no Odometry topic and no /tf: monocular run")
        resolved = OdometrySourceKind.NONE
    return odo, resolved


def select_topics(bag: BagReader, rc: RosbagConfig) -> Selection:
    """The topic of each role (images, camera_info, ground truth, wheel odometry): named in the config, or
    auto-detected; a role that cannot be decided carries its problem."""
    image = _image_choice(bag, rc)
    info = _camera_info_choice(bag, rc, image)
    gt = _groundtruth_choice(bag, rc)
    odo, resolved = _odometry_choice(bag, rc, gt)
    return Selection(image, info, gt, odo, resolved)


# ---------------------------------------------------------------------------- small topics, one pass


def _T_from_pose(pose) -> np.ndarray:
    q = pose.orientation
    p = pose.position
    return make_T(R_from_quat(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


def _T_from_transform(tr) -> np.ndarray:
    q = tr.rotation
    p = tr.translation
    return make_T(R_from_quat(np.array([q.x, q.y, q.z, q.w])), np.array([p.x, p.y, p.z]))


@dataclass
class AuxData:
    camera_info: Any = None
    odometry: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (t ns, T_odom_base)
    odometry_frames: tuple[str, str] | None = None  # (header frame, child frame) of Odometry messages
    static_edges: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (parent, child) -> T
    tf_pairs: Counter = field(default_factory=Counter)  # (parent, child) -> count on /tf
    tf_samples: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = field(default_factory=dict)
    groundtruth: list[tuple[int, np.ndarray]] = field(default_factory=list)
    damage: str | None = None


def read_aux(bag: BagReader, sel: Selection, rc: RosbagConfig) -> AuxData:
    """camera_info (first message), odometry, /tf_static, the wanted /tf pairs and ground truth, in one pass."""
    aux = AuxData()
    topics = {t for t in (sel.camera_info.topic, sel.groundtruth.topic) if t}
    if sel.odometry.topic and not sel.odometry.problem:
        topics.add(sel.odometry.topic)
    topics |= {t for t in (TF_TOPIC, TF_STATIC_TOPIC) if t in bag.topics and bag.topics[t].msgtype in TF_TYPES}
    odom_frame = _norm_frame(rc.odom_frame)
    gt_pair = ((_norm_frame(rc.groundtruth_parent_frame), _norm_frame(rc.groundtruth_child_frame))
               if rc.groundtruth_parent_frame and rc.groundtruth_child_frame else None)
    types = {t: bag.topics[t].msgtype for t in topics}
    try:
        for topic, t_rec, raw in bag.messages(sorted(topics)):
            if topic == sel.camera_info.topic:
                if aux.camera_info is None:  # one is enough: the calibration does not change
                    aux.camera_info = bag.deserialize(raw, CAMERA_INFO)
                continue
            msg = bag.deserialize(raw, types[topic])
            if topic == TF_STATIC_TOPIC:
                for tr in msg.transforms:
                    key = (_norm_frame(tr.header.frame_id), _norm_frame(tr.child_frame_id))
                    aux.static_edges[key] = _T_from_transform(tr.transform)
            elif topic == TF_TOPIC:
                for tr in msg.transforms:
                    key = (_norm_frame(tr.header.frame_id), _norm_frame(tr.child_frame_id))
                    aux.tf_pairs[key] += 1
                    if key[0] == odom_frame or key == gt_pair:
                        aux.tf_samples.setdefault(key, []).append((_stamp_ns(tr.header, t_rec),
                                                                   _T_from_transform(tr.transform)))
            elif topic == sel.odometry.topic and sel.odometry_source is OdometrySourceKind.MESSAGE:
                aux.odometry.append((_stamp_ns(msg.header, t_rec), _T_from_pose(msg.pose.pose)))
                if aux.odometry_frames is None:
                    aux.odometry_frames = (_norm_frame(msg.header.frame_id), _norm_frame(msg.child_frame_id))
            if topic == sel.groundtruth.topic and topic != TF_TOPIC:
                pose = msg.pose.pose if types[topic] == ODOMETRY else msg.pose
                aux.groundtruth.append((_stamp_ns(msg.header, t_rec), _T_from_pose(pose)))
    except BagDamage as err:
        aux.damage = str(err)
    if gt_pair is not None:
        aux.groundtruth = aux.tf_samples.get(gt_pair, [])
    return aux


# ---------------------------------------------------------------------------- frames and calibration


def static_chain(edges: dict[tuple[str, str], np.ndarray], src: str, dst: str) -> np.ndarray | None:
    """T_src_dst through the static transforms (traversed in either direction), or None without a path."""
    adj: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T_parent_child in edges.items():
        adj.setdefault(parent, []).append((child, T_parent_child))
        adj.setdefault(child, []).append((parent, inv_T(T_parent_child)))
    if src not in adj or dst not in adj:
        return np.eye(4) if src == dst else None
    best: dict[str, np.ndarray] = {src: np.eye(4)}
    queue = [src]
    while queue:
        a = queue.pop(0)
        for b, T_ab in adj[a]:
            if b not in best:
                best[b] = best[a] @ T_ab
                queue.append(b)
    return best.get(dst)


def camera_from_info(info, topic: str) -> CameraModel:
    """Intrinsics of a sensor_msgs/CameraInfo (T_base_cam left at identity for the caller to set)."""
    fields = info.__dataclass_fields__ if hasattr(info, "__dataclass_fields__") else {}
    K = np.asarray(info.K if "K" in fields else info.k, float).ravel()
    D = [float(x) for x in np.asarray(info.D if "D" in fields else info.d, float).ravel()]
    model = str(info.distortion_model).strip().lower()
    if K.size != 9 or K[0] <= 0 or K[4] <= 0:
        raise CalibrationError(f"camera_info on {topic} has no calibration (K is zero): add a camera: section "
                               "to the config")
    dist: tuple[float, ...]
    if model in ("plumb_bob", "radtan", "") and not any(D):
        dm, dist = DistortionModel.NONE, ()  # drivers of uncalibrated or rectified cameras leave D empty
    elif model in ("plumb_bob", "radtan") or (model == "" and D):
        if len(D) not in (4, 5):
            raise CalibrationError(f"camera_info on {topic}: plumb_bob needs 4 or 5 coefficients, got {len(D)}")
        dm, dist = DistortionModel.RADTAN, tuple(D)
    elif model == "rational_polynomial":
        if len(D) < 5:
            raise CalibrationError(f"camera_info on {topic}: rational_polynomial needs 8 coefficients, got {len(D)}")
        if any(abs(x) > 0 for x in D[5:]):
            raise CalibrationError(
                f"camera_info on {topic}: rational_polynomial with non-zero k4..k6 ({', '.join(f'{x:g}' for x in D[5:8])}) "
                "cannot be expressed as radtan; calibrate with plumb_bob or give a camera: section in the config")
        dm, dist = DistortionModel.RADTAN, tuple(D[:5])
    elif model in ("equidistant", "fisheye"):
        if len(D) != 4:
            raise CalibrationError(f"camera_info on {topic}: equidistant needs 4 coefficients, got {len(D)}")
        dm, dist = DistortionModel.EQUIDISTANT, tuple(D)
    elif model == "none" and not any(D):
        dm, dist = DistortionModel.NONE, ()
    else:
        raise CalibrationError(f"camera_info on {topic}: distortion model '{info.distortion_model}' is not supported "
                               "(plumb_bob, rational_polynomial, equidistant)")
    return CameraModel(int(info.width), int(info.height), float(K[0]), float(K[4]), float(K[2]), float(K[5]),
                       dm, dist, np.eye(4))


def _planar_odometry(samples: list[tuple[int, np.ndarray]], label: str) -> WheelOdometry | None:
    if len(samples) < 2:
        return None
    samples = sorted(samples, key=lambda s: s[0])
    ts: list[int] = []
    keep: list[np.ndarray] = []
    for t, T in samples:
        if ts and t <= ts[-1]:
            continue
        ts.append(t)
        keep.append(T)
    Ts = np.stack(keep)
    yaw = np.unwrap(np.arctan2(Ts[:, 1, 0], Ts[:, 0, 0]))
    return WheelOdometry(np.asarray(ts, float) * 1e-9, Ts[:, 0, 3].copy(), Ts[:, 1, 3].copy(), yaw, comment=label)


def _groundtruth_at(samples: list[tuple[int, np.ndarray]], times: np.ndarray) -> Trajectory | None:
    if len(samples) < 2:
        return None
    samples = sorted(samples, key=lambda s: s[0])
    t_src = np.asarray([s[0] for s in samples], float) * 1e-9
    keep = np.concatenate([[True], np.diff(t_src) > 0])
    T_src = np.stack([s[1] for s in samples])[keep]
    T_img, inside = interp_poses(t_src[keep], T_src, times)
    if inside.sum() < 2:
        return None
    return anchor(times[inside], T_img[inside])


# ---------------------------------------------------------------------------- the loader


@dataclass
class ImageIndex:
    timestamps: np.ndarray  # s
    ordinals: np.ndarray  # position among the topic's messages in the window
    first_msg: Any
    frame_id: str
    dropped: int  # frames whose stamp did not increase
    damage: str | None


# A header stamp whose offset from the record time changes by more than this between two frames
# is a damaged stamp (a flipped byte of its seconds), not clock drift.
STAMP_JUMP_NS = 10 * 1_000_000_000
JPEG_MAGIC, PNG_MAGIC = b"\xff\xd8", b"\x89PNG"


def _bytes_per_pixel(encoding: str) -> int | None:
    if encoding in MONO8 or encoding in BAYER_CODES:
        return 1
    if encoding in MONO16:
        return 2
    return COLOR_CODES[encoding][0] if encoding in COLOR_CODES else None


def image_layout(msg, msgtype: str) -> tuple:
    """What must stay the same from frame to frame: frame id, then format, or encoding, size, step, data length.

    Raises :class:`BagDamage` for a message that is inconsistent in itself (a stamp's nanoseconds
    not below 1 s, image data shorter than height x step, a step below width x bytes per pixel,
    compressed data without the JPEG / PNG signature its format names).
    """
    if not 0 <= int(msg.header.stamp.nanosec) < 1_000_000_000:
        raise BagDamage(f"header stamp with {msg.header.stamp.nanosec} ns")
    frame = _norm_frame(msg.header.frame_id)
    data = msg.data
    if msgtype == COMPRESSED_IMAGE:
        fmt = str(msg.format).lower()
        head = bytes(np.asarray(data[:4], dtype=np.uint8))
        if "compresseddepth" in fmt:  # a header before the PNG; the decoder rejects these anyway
            return frame, fmt
        if ("jpeg" in fmt and not head.startswith(JPEG_MAGIC)) or ("png" in fmt and not head.startswith(PNG_MAGIC)):
            raise BagDamage(f"compressed image data does not start like its format ('{msg.format}')")
        return frame, fmt
    enc = str(msg.encoding).lower()
    h, w, step, n = int(msg.height), int(msg.width), int(msg.step), len(data)
    bpp = _bytes_per_pixel(enc)
    if h <= 0 or w <= 0 or n < h * step or (bpp is not None and step < w * bpp):
        raise BagDamage(f"image {w}x{h} '{msg.encoding}' with step {step} and {n} data bytes")
    return frame, enc, h, w, step, int(msg.is_bigendian), n


def _layout_change(prev: tuple, cur: tuple) -> str:
    return f"image layout changed from {prev} to {cur} (frame id, encoding, height, width, step, endianness, bytes)"


def index_images(bag: BagReader, topic: str, start_ns: int | None, stop_ns: int | None) -> ImageIndex:
    """Timestamps of every frame on the topic (one pass, nothing kept but the stamps and the first message).

    Every message is checked (:func:`image_layout`): one that is inconsistent in itself, differs
    from the first one's layout, or whose stamp jumps against the record time, is damage, and the
    index stops before it.
    """
    msgtype = bag.topics[topic].msgtype
    stamps: list[int] = []
    ordinals: list[int] = []
    first, frame_id, dropped, damage = None, "", 0, None
    layout: tuple = ()
    offset: int | None = None  # header stamp - record time of the last stamped frame
    n_ok = 0  # messages read and checked
    try:
        for k, (_topic, t_rec, raw) in enumerate(bag.messages([topic], start_ns, stop_ns)):
            msg = bag.deserialize(raw, msgtype)
            cur = image_layout(msg, msgtype)
            if first is None:
                first, frame_id, layout = msg, _norm_frame(msg.header.frame_id), cur
            elif cur != layout:
                raise BagDamage(_layout_change(layout, cur))
            t = _stamp_ns(msg.header, t_rec)
            if t != t_rec:
                if offset is not None and abs(t - t_rec - offset) > STAMP_JUMP_NS:
                    raise BagDamage(f"header stamp jumps by {(t - t_rec - offset) * 1e-9:.0f} s against the record time")
                offset = t - t_rec
            n_ok += 1
            if stamps and t <= stamps[-1]:
                dropped += 1
                continue
            stamps.append(t)
            ordinals.append(k)
    except BagDamage as err:
        damage = f"{err}, after {n_ok} good messages on {topic}"
    return ImageIndex(np.asarray(stamps, float) * 1e-9, np.asarray(ordinals, dtype=np.int64), first, frame_id,
                      dropped, damage)


def _camera_model(cam_cfg: CameraConfig | None, aux: AuxData, sel: Selection, warnings: list[str]) -> CameraModel:
    if cam_cfg is not None:
        if aux.camera_info is not None:
            warnings.append("intrinsics from the config's camera section (it wins over the bag's camera_info)")
        T = np.asarray(cam_cfg.T_base_cam, float).reshape(4, 4) if cam_cfg.T_base_cam is not None else np.eye(4)
        return CameraModel(cam_cfg.width, cam_cfg.height, cam_cfg.fx, cam_cfg.fy, cam_cfg.cx, cam_cfg.cy,
                           DistortionModel(cam_cfg.distortion_model), tuple(cam_cfg.distortion), T)
    if sel.camera_info.problem:
        raise SequenceError(sel.camera_info.problem)
    if aux.camera_info is None:
        where = f"{sel.camera_info.topic} has no readable message" if sel.camera_info.topic else "no camera_info topic"
        raise CalibrationError(f"no intrinsics: {where} in the bag and no camera: section in the config")
    return camera_from_info(aux.camera_info, sel.camera_info.topic or "")


def _frames_text(edges: dict[tuple[str, str], np.ndarray]) -> str:
    return ", ".join(f"{p} -> {c}" for p, c in sorted(edges))


def resolve_T_base_cam(rc: RosbagConfig, cam_cfg: CameraConfig | None, aux: AuxData, base_frame: str,
                       camera_frame: str, has_tf_static: bool, warnings: list[str]) -> tuple[np.ndarray, str]:
    if cam_cfg is not None and cam_cfg.T_base_cam is not None:
        return np.asarray(cam_cfg.T_base_cam, float).reshape(4, 4), "camera.T_base_cam from the config"
    if not has_tf_static or not aux.static_edges:
        warnings.append("no /tf_static and no camera.T_base_cam: camera assumed at the base origin looking forward")
        return T_BASE_CAM_FORWARD.copy(), "default (forward-looking camera at the base origin)"
    if not camera_frame:
        raise CalibrationError("the camera frame is unknown (empty frame_id in camera_info and images): "
                               "set rosbag.camera_frame")
    T = static_chain(aux.static_edges, base_frame, camera_frame)
    if T is None:
        raise CalibrationError(
            f"/tf_static has no path from the base frame '{base_frame}' to the camera frame '{camera_frame}'; "
            f"it has: {_frames_text(aux.static_edges)} (set rosbag.base_frame / rosbag.camera_frame, "
            "or camera.T_base_cam)")
    return T, f"/tf_static {base_frame} -> {camera_frame}"


def _base_frame(rc: RosbagConfig, aux: AuxData, odom_child: str | None) -> str:
    if rc.base_frame:
        return _norm_frame(rc.base_frame)
    if odom_child:
        return odom_child
    frames = {f for e in aux.static_edges for f in e}
    for f in ("base_link", "base_footprint"):
        if f in frames:
            return f
    return "base_link"


def _tf_odometry(aux: AuxData, rc: RosbagConfig) -> tuple[list[tuple[int, np.ndarray]], str | None, str]:
    """Samples of odom_frame -> base on /tf, the child frame used, and a note."""
    odom = _norm_frame(rc.odom_frame)
    children = sorted(c for (p, c) in aux.tf_samples if p == odom)
    if rc.base_frame:
        child = _norm_frame(rc.base_frame)
        return aux.tf_samples.get((odom, child), []), child, f"/tf {odom} -> {child}"
    if len(children) == 1:
        return aux.tf_samples[(odom, children[0])], children[0], f"/tf {odom} -> {children[0]}"
    for f in ("base_link", "base_footprint"):
        if f in children:
            return aux.tf_samples[(odom, f)], f, f"/tf {odom} -> {f}"
    return [], None, f"no /tf transform from '{odom}'" + (f" (children: {', '.join(children)})" if children else "")


def load_rosbag(path: Path, rc: RosbagConfig, cam_cfg: CameraConfig | None) -> StreamedSequence:
    path = Path(path)
    readers = [BagReader(path)]
    try:
        return _load(readers, path, rc, cam_cfg)
    finally:
        for r in readers:
            r.close()


def _index_or_salvage(bag: BagReader, topic: str, start_ns: int | None,
                      stop_ns: int | None) -> tuple[ImageIndex, BagReader]:
    """Index the image topic; if an intact index leads to damaged data, also try a sequential scan."""
    idx = index_images(bag, topic, start_ns, stop_ns)
    if idx.damage is None or bag.damage is not None:
        return idx, bag
    try:
        seq_bag = BagReader(bag.path, salvage=idx.damage)
    except SequenceError:
        return idx, bag
    if topic in seq_bag.topics:
        idx2 = index_images(seq_bag, topic, start_ns, stop_ns)
        if len(idx2.timestamps) > len(idx.timestamps):
            return idx2, seq_bag
    seq_bag.close()
    return idx, bag


def _wheel_odometry(sel: Selection, aux: AuxData, rc: RosbagConfig,
                    warnings: list[str]) -> tuple[WheelOdometry | None, str | None]:
    """The bag's wheel odometry (from Odometry messages or /tf) and the base frame it names (its child)."""
    odometry = None
    odom_child: str | None = None
    if sel.odometry_source is OdometrySourceKind.MESSAGE:
        odometry = _planar_odometry(aux.odometry, f"wheel odometry from {sel.odometry.topic} (nav_msgs/Odometry)")
        if odometry is None:
            raise SequenceError(f"odometry topic {sel.odometry.topic} has fewer than 2 readable messages")
        odom_child = aux.odometry_frames[1] if aux.odometry_frames else None
    elif sel.odometry_source is OdometrySourceKind.TF:
        samples, odom_child, note = _tf_odometry(aux, rc)
        odometry = _planar_odometry(samples, f"wheel odometry from {note}")
        if odometry is None:
            if rc.odometry_source is OdometrySourceKind.TF:
                raise SequenceError(f"rosbag.odometry_source is tf but {note} in the bag's /tf "
                                    f"(pairs: {', '.join(f'{p} -> {c}' for p, c in sorted(aux.tf_pairs)) or 'none'})")
            warnings.append(f"no wheel odometry: {note}")
            odom_child = None
    return odometry, odom_child


def _image_index(bag: BagReader, path: Path, image_topic: str, rc: RosbagConfig, readers: list[BagReader],
                 warnings: list[str]):
    """The image topic's index within the configured time window (salvaged up to any damage)."""
    start_ns = bag.start_ns + round(rc.start_s * 1e9) if rc.start_s > 0 else None
    stop_ns = bag.start_ns + round(rc.end_s * 1e9) if rc.end_s is not None else None
    idx, bag = _index_or_salvage(bag, image_topic, start_ns, stop_ns)
    readers.append(bag)
    damage = idx.damage or bag.damage
    if damage:
        if len(idx.timestamps) == 0:
            raise SequenceError(f"bag {path}: no readable image on {image_topic} ({damage})")
        warnings.append(f"bag is damaged ({damage}): using the {len(idx.timestamps)} frames on {image_topic} "
                        "before the damage")
    if len(idx.timestamps) == 0:
        window = "" if start_ns is None and stop_ns is None else " in the rosbag.start_s / end_s window"
        raise SequenceError(f"no image on {image_topic}{window}")
    if idx.dropped:
        warnings.append(f"{idx.dropped} frame(s) on {image_topic} dropped: their stamp did not increase")
    return idx, bag, start_ns, stop_ns


def _load(readers: list[BagReader], path: Path, rc: RosbagConfig, cam_cfg: CameraConfig | None) -> StreamedSequence:
    bag = readers[0]
    warnings: list[str] = []
    sel = select_topics(bag, rc)
    for ch in (sel.image, sel.odometry, sel.groundtruth):
        if ch.problem:
            raise SequenceError(ch.problem + (f" (the bag is damaged: {bag.damage})" if bag.damage else ""))
    image_topic = sel.image.topic
    assert image_topic is not None
    msgtype = bag.topics[image_topic].msgtype
    idx, bag, start_ns, stop_ns = _image_index(bag, path, image_topic, rc, readers, warnings)
    times = idx.timestamps
    aux = read_aux(bag, sel, rc)
    if aux.damage:
        warnings.append(f"bag damaged while reading camera_info/odometry/tf ({aux.damage}): using what came before")

    camera = _camera_model(cam_cfg, aux, sel, warnings)
    decoder = ImageDecoder(image_topic)
    try:
        first = decoder.decode(idx.first_msg, msgtype)
    except FrameError as err:
        raise SequenceError(f"first image on {image_topic} cannot be used: {err}") from None
    if first.shape != (camera.height, camera.width):
        src = "the config's camera section" if cam_cfg is not None else f"camera_info on {sel.camera_info.topic}"
        raise CalibrationError(f"{src} says {camera.width}x{camera.height} but the images on {image_topic} are "
                               f"{first.shape[1]}x{first.shape[0]}")

    odometry, odom_child = _wheel_odometry(sel, aux, rc, warnings)
    if odometry is not None:
        warnings.extend(check_odometry_overlap(odometry, times))

    # frames and mounting
    base_frame = _base_frame(rc, aux, odom_child)
    info_frame = _norm_frame(aux.camera_info.header.frame_id) if aux.camera_info is not None else ""
    camera_frame = _norm_frame(rc.camera_frame) if rc.camera_frame else (info_frame or idx.frame_id)
    T_base_cam, how = resolve_T_base_cam(rc, cam_cfg, aux, base_frame, camera_frame,
                                         TF_STATIC_TOPIC in bag.topics, warnings)
    camera = CameraModel(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                         camera.distortion_model, camera.distortion, T_base_cam)
    log.info("rosbag %s: images %s (%d frames), T_base_cam from %s", path.name, image_topic, len(times), how)

    groundtruth = None
    if sel.groundtruth.topic:
        groundtruth = _groundtruth_at(aux.groundtruth, times)
        if groundtruth is None:
            warnings.append(f"ground truth ({sel.groundtruth.reason}) does not cover 2 image times: not used")

    source = BagFrameSource(path, image_topic, msgtype, idx.ordinals, start_ns, stop_ns, decoder, salvage=bag.damage)
    return StreamedSequence(path, [], times, camera, odometry, groundtruth, warnings,
                            name=path.stem if path.is_file() else path.name, source=source)


# ---------------------------------------------------------------------------- inspection (topics CLI)


@dataclass
class TopicStats:
    name: str
    msgtype: str
    count: int
    rate_hz: float | None  # from the first and last record times


def topic_stats(bag: BagReader) -> list[TopicStats]:
    """Counts and mean rates per topic (one pass over the record times; message bodies are not decoded)."""
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    n: Counter = Counter()
    try:
        for topic, t_ns, _raw in bag.messages(sorted(bag.topics)):
            first.setdefault(topic, t_ns)
            last[topic] = t_ns
            n[topic] += 1
    except BagDamage:
        pass
    out = []
    for top in sorted(bag.topics.values(), key=lambda x: x.name):
        span = (last.get(top.name, 0) - first.get(top.name, 0)) * 1e-9
        rate = (n[top.name] - 1) / span if n[top.name] > 1 and span > 0 else None
        out.append(TopicStats(top.name, top.msgtype, top.count, rate))
    return out


def describe_usage(bag: BagReader, rc: RosbagConfig, cam_cfg: CameraConfig | None) -> list[str]:
    """What the loader would use for each role, and why (or what is ambiguous or missing)."""
    sel = select_topics(bag, rc)
    lines = [sel.image.line()]
    aux = read_aux(bag, sel, rc)
    if cam_cfg is not None:
        lines.append("camera_info: not needed (the config's camera section wins)")
    else:
        lines.append(sel.camera_info.line())
    if sel.odometry.problem:
        lines.append(sel.odometry.line())
        odom_child = None
    elif sel.odometry_source is OdometrySourceKind.TF:
        samples, odom_child, note = _tf_odometry(aux, rc)
        lines.append(f"odometry: {note} ({len(samples)} transforms)" if samples else f"odometry: none ({note})")
    elif sel.odometry_source is OdometrySourceKind.MESSAGE:
        odom_child = aux.odometry_frames[1] if aux.odometry_frames else None
        lines.append(sel.odometry.line() + (f", base frame '{odom_child}'" if odom_child else ""))
    else:
        odom_child = None
        lines.append(sel.odometry.line())
    base = _base_frame(rc, aux, odom_child)
    info_frame = _norm_frame(aux.camera_info.header.frame_id) if aux.camera_info is not None else ""
    cam_frame = _norm_frame(rc.camera_frame) if rc.camera_frame else info_frame
    if cam_cfg is not None and cam_cfg.T_base_cam is not None:
        lines.append("tf: camera.T_base_cam from the config")
    elif not aux.static_edges:
        lines.append("tf: no /tf_static: camera assumed at the base origin looking forward (or set camera.T_base_cam)")
    else:
        T = static_chain(aux.static_edges, base, cam_frame) if cam_frame else None
        if T is None:
            lines.append(f"tf: ? no /tf_static path from '{base}' to '{cam_frame or '(unknown camera frame)'}'; "
                         f"it has {_frames_text(aux.static_edges)}")
        else:
            lines.append(f"tf: /tf_static {base} -> {cam_frame} (T_base_cam translation "
                         f"{', '.join(f'{x:.3f}' for x in T[:3, 3])} m)")
    if aux.tf_pairs:
        lines.append("    /tf carries: " + ", ".join(f"{p} -> {c} ({k})" for (p, c), k in sorted(aux.tf_pairs.items())))
    lines.append(sel.groundtruth.line())
    if bag.damage:
        lines.append(f"damaged bag: {bag.damage}")
    return lines



def load(cfg: Config) -> StreamedSequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_rosbag(cfg.sequence, cfg.rosbag, cfg.camera)
