"""Damaged input: truncated and byte-flipped bags, float spellings in camera.yaml, the topics CLI's type names.

Bags are written with ``windowvo.synth.bagwriter`` from a small rendered sequence (160x120,
40 frames), then damaged on disk; the salvaged frames must equal the native ones.
"""

from __future__ import annotations

import re
import sqlite3
import struct
from pathlib import Path

import numpy as np
import pytest

from windowvo.cli.topics import main as topics_main
from windowvo.config import RosbagConfig
from windowvo.errors import CalibrationError
from windowvo.io.bagsalvage import Damage, SalvageMessage, scan_ros1, scan_sqlite
from windowvo.io.rosbag import load_rosbag
from windowvo.io.sequence import load_native, read_camera_yaml, safe_load_yaml
from windowvo.synth.bagwriter import EPOCH, BagSpec, write_bag
from windowvo.synth.paths import PathKind
from windowvo.tools.topics import report

W, H, N = 160, 120, 40


@pytest.fixture(scope="module")
def native(seq_factory) -> Path:
    return seq_factory("faults_small", path=PathKind.LOOP, duration_s=3.0, seed=8, width=W, height=H)


@pytest.fixture(scope="module")
def bags(native, tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("fault_bags")
    return {st: write_bag(native, out / (st + (".bag" if st == "ros1" else "")), BagSpec(storage=st, max_frames=N))
            for st in ("ros1", "sqlite3", "mcap")}


def _copy_bag(src: Path, dst: Path) -> tuple[Path, Path]:
    """A copy of the bag and its data file (the .bag itself, or the folder's .db3 / .mcap)."""
    if src.is_file():
        dst.write_bytes(src.read_bytes())
        return dst, dst
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst, next(f for f in dst.iterdir() if f.suffix in (".db3", ".mcap"))


def _assert_native_prefix(seq, native: Path) -> None:
    nat = load_native(native)
    assert np.allclose(seq.timestamps - EPOCH, nat.timestamps[: len(seq)], atol=1e-6)
    for i in range(len(seq)):
        assert np.array_equal(seq.read_image(i), nat.read_image(i)), i


# ---------------------------------------------------------------------------- truncated ROS 2 .db3


def test_truncated_sqlite_bag_uses_the_frames_before_the_cut(native, bags, tmp_path):
    bag, db = _copy_bag(bags["sqlite3"], tmp_path / "cut")
    data = db.read_bytes()
    db.write_bytes(data[: int(len(data) * 0.55)])
    seq = load_rosbag(bag, RosbagConfig(), None)
    assert 15 < len(seq) < N
    damage = [w for w in seq.warnings if "damaged" in w]
    assert len(damage) == 1 and f"using the {len(seq)} frames on /camera/image_raw before the damage" in damage[0]
    assert "of its" in damage[0]  # says how much of the file is left
    _assert_native_prefix(seq, native)
    assert seq.odometry is not None


def test_sqlite_cuts_anywhere_salvage_only_intact_rows(bags, tmp_path):
    """Every cut position: the rows read are exactly the first rows of the intact bag, never zero-padded ones."""
    src = next(bags["sqlite3"].glob("*.db3"))
    data = src.read_bytes()
    with sqlite3.connect(src) as con:
        rows = con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY rowid").fetchall()
    cut_file = tmp_path / "c.db3"
    # a fine sweep over one stretch (every kind of page gets cut: leaves, overflow, both mid-page) plus a coarse one
    cuts = list(range(len(data) // 2, len(data) // 2 + 24 * 4096, 1021)) + list(range(40_000, len(data), 37_000))
    read_counts = []
    for c in cuts:
        cut_file.write_bytes(data[:c])
        got = []
        with pytest.raises(Damage):
            for rec in scan_sqlite(cut_file):
                if isinstance(rec, SalvageMessage):
                    got.append((rec.cid, rec.time_ns, rec.data))
        assert got == [tuple(r) for r in rows[: len(got)]], c
        read_counts.append(len(got) / len(rows) / (c / len(data)))
    assert np.mean(read_counts) > 0.8  # close to everything before the cut


# ---------------------------------------------------------------------------- flipped bytes in a ROS 1 bag


def _image_field_offsets(data: bytes) -> list[int]:
    """Offset of the width/height fields of every mono8 image message (right after the frame id)."""
    frame = b"camera_optical_frame"
    after = struct.pack("<III", H, W, 5) + b"mono8"
    return [m.end() for m in re.finditer(re.escape(frame), data) if data[m.end(): m.end() + len(after)] == after]


# field -> offset from the end of the frame id (stamp sec, nsec, frame id length and text, then height, width,
# encoding length and text, is_bigendian, step), and xor mask
FLIPS = {
    "height": (0, 0x5A),
    "width": (4, 0x01),
    "encoding": (14, 0x01),  # mono8 -> mooo8: still valid UTF-8
    "step": (18, 0x02),
    "frame_id": (-3, 0x20),  # a letter of the frame id changes case
    "stamp_seconds": (-32, 0x5A),  # low byte of header.stamp.sec (jumps ~90 s)
    "conn_key": (None, 0x20),  # the record header's 'conn=' key: 'cOnn='
}


@pytest.mark.parametrize("field", list(FLIPS))
def test_flipped_image_message_stops_the_read_before_it(native, bags, tmp_path, field):
    bag = tmp_path / "flip.bag"
    data = bytearray(bags["ros1"].read_bytes())
    offsets = _image_field_offsets(bytes(data))
    assert len(offsets) == N
    k = 21  # the 22nd image is damaged
    rel, mask = FLIPS[field]
    if rel is None:
        at = data.rfind(b"conn=", 0, offsets[k]) + 1
    else:
        at = offsets[k] + rel
    data[at] ^= mask
    bag.write_bytes(bytes(data))
    seq = load_rosbag(bag, RosbagConfig(), None)
    assert len(seq) == k
    damage = [w for w in seq.warnings if "damaged" in w]
    assert len(damage) == 1 and f"using the {k} frames" in damage[0], seq.warnings
    _assert_native_prefix(seq, native)


def test_ros1_scan_rejects_invalid_op_codes_and_undefined_connections(bags, tmp_path):
    data = bags["ros1"].read_bytes()
    offsets = _image_field_offsets(data)
    ops = [m.start() for m in re.finditer(re.escape(b"op=\x02"), data)]
    op_at = max(o for o in ops if o < offsets[10]) + 3  # the op code of the 11th image's record
    bad = tmp_path / "op.bag"
    bad.write_bytes(data[:op_at] + b"\x09" + data[op_at + 1:])
    n_ok = _count_until_damage(bad, "invalid record op code")
    assert 10 <= n_ok < len(_all_messages(bags["ros1"]))
    conn_at = data.rfind(b"conn=", 0, offsets[10]) + 5  # its connection id: one that was never defined
    bad.write_bytes(data[:conn_at] + b"\x63" + data[conn_at + 1:])
    assert _count_until_damage(bad, "never defined") == n_ok


def _all_messages(path: Path) -> list:
    return [r for r in scan_ros1(path) if isinstance(r, SalvageMessage)]


def _count_until_damage(path: Path, needle: str) -> int:
    n = 0
    with pytest.raises(Damage, match=needle):
        for rec in scan_ros1(path):
            n += isinstance(rec, SalvageMessage)
    return n


# ---------------------------------------------------------------------------- camera.yaml floats


@pytest.mark.parametrize("spelling, value", [("3.4e2", 340.0), ("3.4E+2", 340.0), ("340", 340.0), ("340.0", 340.0),
                                             ("34e1", 340.0), ("3400e-1", 340.0), ("+3.4e2", 340.0)])
def test_camera_yaml_reads_every_float_spelling(native, tmp_path, spelling, value):
    text = (native / "camera.yaml").read_text()
    lines = [f"fx: {spelling}" if ln.startswith("fx:") else ln for ln in text.splitlines()]
    assert any(ln == f"fx: {spelling}" for ln in lines)
    (tmp_path / "camera.yaml").write_text("\n".join(lines) + "\n")
    cam = read_camera_yaml(tmp_path / "camera.yaml")
    assert cam.fx == value
    assert cam.fy == read_camera_yaml(native / "camera.yaml").fy


def test_safe_load_yaml_types():
    d = safe_load_yaml("a: 1e-3\nb: 340\nc: 0x1F\nd: 1.2.3\ne: e3\nf: .inf\ng: -.5E3\nh: '3.4e2'\ni: 1_000.5\n")
    assert d == {"a": 0.001, "b": 340, "c": 31, "d": "1.2.3", "e": "e3", "f": float("inf"), "g": -500.0,
                 "h": "3.4e2", "i": 1000.5}
    assert isinstance(d["b"], int) and isinstance(d["a"], float)


def test_camera_yaml_still_rejects_non_numbers(native, tmp_path):
    text = (native / "camera.yaml").read_text()
    (tmp_path / "camera.yaml").write_text(re.sub(r"(?m)^fx:.*$", "fx: 3.4e", text))
    with pytest.raises(CalibrationError, match="'fx' must be a number"):
        read_camera_yaml(tmp_path / "camera.yaml")


# ---------------------------------------------------------------------------- topics CLI


def test_topics_prints_each_bags_types_in_its_own_convention(bags):
    ros1 = report(bags["ros1"], RosbagConfig(), None)
    assert "| /camera/image_raw | sensor_msgs/Image | 40 |" in ros1
    assert "| /odom | nav_msgs/Odometry |" in ros1 and "/msg/" not in ros1
    ros2 = report(bags["mcap"], RosbagConfig(), None)
    assert "| /camera/image_raw | sensor_msgs/msg/Image | 40 |" in ros2


def test_topics_help_has_no_backticks(capsys):
    with pytest.raises(SystemExit) as ex:
        topics_main(["--help"])
    assert ex.value.code == 0
    out = capsys.readouterr().out
    assert "python -m windowvo.topics BAG: what a ROS bag holds" in " ".join(out.split())
    assert "`" not in out
