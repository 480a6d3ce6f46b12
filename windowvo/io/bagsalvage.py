"""Sequential readers for damaged bags: the messages before the damage, without the index.

A recording that was killed (power loss, full disk) leaves a ROS 1 bag or an MCAP file
without its index, and ``rosbags`` refuses to open it. Both formats are a plain sequence of
records, so the records can be scanned from the start until the first one that is cut off
or unreadable. ``scan_*`` yields :class:`SalvageRecord` items: connection definitions as
they appear, then messages (record time in ns and the serialised bytes).

A ROS 2 SQLite bag (``.db3``) is read row by row in insertion order until SQLite reports
the damage (``scan_sqlite``), also when the file is cut off (SQLite is opened leniently, see
``_sqlite_connect``); a database whose schema itself is damaged yields nothing.
"""

from __future__ import annotations

import bz2
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"


class Damage(Exception):
    """The scan reached a record that is cut off or malformed (the message says where)."""


@dataclass
class SalvageConnection:
    cid: int
    topic: str
    msgtype: str  # ROS 1 / ROS 2 form as stored, e.g. sensor_msgs/Image or sensor_msgs/msg/Image
    msgdef: str  # message definition text ('' when unknown)
    msgdef_format: str  # msg | idl | ''


@dataclass
class SalvageMessage:
    cid: int
    time_ns: int
    data: bytes


SalvageRecord = SalvageConnection | SalvageMessage


# ---------------------------------------------------------------------------- ROS 1


def _ros1_fields(buf: bytes) -> dict[str, bytes]:
    fields = {}
    pos = 0
    while pos < len(buf):
        if pos + 4 > len(buf):
            raise Damage("record header cut off")
        (n,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        if pos + n > len(buf):
            raise Damage("record header field cut off")
        item = buf[pos : pos + n]
        pos += n
        key, sep, value = item.partition(b"=")
        if not sep:
            raise Damage("record header field without '='")
        fields[key.decode("latin-1")] = value
    return fields


def _ros1_records(buf: bytes) -> Iterator[tuple[dict[str, bytes], bytes]]:
    """Records inside a (decompressed) chunk; raises Damage at the first incomplete one."""
    pos = 0
    while pos < len(buf):
        if pos + 4 > len(buf):
            raise Damage("chunk record cut off")
        (hlen,) = struct.unpack_from("<I", buf, pos)
        if pos + 4 + hlen + 4 > len(buf):
            raise Damage("chunk record cut off")
        header = _ros1_fields(buf[pos + 4 : pos + 4 + hlen])
        pos += 4 + hlen
        (dlen,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        if pos + dlen > len(buf):
            raise Damage("chunk record cut off")
        yield header, buf[pos : pos + dlen]
        pos += dlen


ROS1_OPS = {b"\x02": "message data", b"\x03": "bag header", b"\x04": "index data", b"\x05": "chunk",
            b"\x06": "chunk info", b"\x07": "connection"}
ROS1_CHUNK_OPS = (b"\x02", b"\x07")  # what a chunk holds


def _ros1_field(header: dict[str, bytes], key: str, fmt: str) -> tuple[int, ...]:
    """A fixed-size header field; Damage when it is missing or has the wrong size (a flipped length)."""
    value = header.get(key)
    if value is None or len(value) != struct.calcsize(fmt):
        raise Damage(f"record header field '{key}' missing or of the wrong size")
    return struct.unpack(fmt, value)


def _ros1_op(header: dict[str, bytes], allowed: tuple[bytes, ...] | None = None) -> bytes:
    op = header.get("op", b"")
    if len(op) != 1 or op not in ROS1_OPS or (allowed is not None and op not in allowed):
        raise Damage(f"invalid record op code {op!r}")
    return op


def _ros1_inner(header: dict[str, bytes], data: bytes, seen: set[int]) -> Iterator[SalvageRecord]:
    op = _ros1_op(header, ROS1_CHUNK_OPS)
    (cid,) = _ros1_field(header, "conn", "<I")
    if op == b"\x07":  # connection
        if cid in seen:
            return
        info = _ros1_fields(data)
        try:
            topic = header.get("topic", info.get("topic", b"")).decode()
            msgtype, text = info.get("type", b"").decode(), info.get("message_definition", b"").decode()
        except UnicodeDecodeError:
            raise Damage("connection record with a malformed topic, type or definition") from None
        if not topic or msgtype.count("/") not in (1, 2):
            raise Damage(f"connection record with a malformed topic '{topic}' or type '{msgtype}'")
        seen.add(cid)
        yield SalvageConnection(cid, topic, msgtype, text, "msg")
    else:  # message data
        if cid not in seen:
            raise Damage(f"message on connection {cid}, which the bag never defined")
        sec, nsec = _ros1_field(header, "time", "<II")
        if nsec >= 1_000_000_000:
            raise Damage(f"message record time with {nsec} ns (not below 1 s)")
        yield SalvageMessage(cid, sec * 1_000_000_000 + nsec, data)


def _decompress_partial(kind: str, data: bytes) -> bytes:
    """As much of a compressed chunk as can be decoded (a cut-off chunk yields its beginning)."""
    if kind == "none":
        return data
    if kind == "bz2":
        try:
            return bz2.BZ2Decompressor().decompress(data)
        except (OSError, EOFError, ValueError) as err:
            raise Damage(f"bz2 chunk cannot be decompressed: {err}") from None
    if kind == "lz4":
        import lz4.frame

        try:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        except RuntimeError as err:
            raise Damage(f"lz4 chunk cannot be decompressed: {err}") from None
    raise Damage(f"unknown chunk compression '{kind}'")


def _read_exact(fh: BinaryIO, n: int, what: str) -> bytes:
    b = fh.read(n)
    if len(b) != n:
        raise Damage(f"{what} cut off at byte {fh.tell()}")
    return b


def _ros1_chunk(fh: BinaryIO, header: dict[str, bytes], dlen: int, seen: set[int]) -> Iterator[SalvageRecord]:
    """The records of one chunk: what is there even when cut off; Damage at the first bad one."""
    data = fh.read(dlen)
    cut = len(data) < dlen
    kind = header.get("compression", b"none").decode("latin-1")
    records = _decompress_partial(kind, data)
    (size,) = _ros1_field(header, "size", "<I")
    if not cut and len(records) != size:
        raise Damage(f"chunk at byte {fh.tell() - dlen} decodes to {len(records)} bytes, its header says {size}")
    for h, d in _ros1_records(records):
        yield from _ros1_inner(h, d, seen)
    if cut:
        raise Damage(f"chunk cut off at byte {fh.tell()}")


def scan_ros1(path: Path) -> Iterator[SalvageRecord]:
    """Connections and messages of a ROS 1 bag in file order, up to the first damaged record.

    Raises :class:`Damage` (after yielding everything before it) when the file is cut off or
    malformed (inconsistent lengths, invalid op codes or field sizes, a chunk that does not
    decode to its stated size, a message on an undefined connection); returns normally at a
    clean end of file.
    """
    seen: set[int] = set()
    with open(path, "rb") as fh:
        if fh.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
            raise Damage("not a ROS 1 bag (no '#ROSBAG V2.0' header)")
        while True:
            head = fh.read(4)
            if not head:
                return
            if len(head) < 4:
                raise Damage(f"record cut off at byte {fh.tell()}")
            (hlen,) = struct.unpack("<I", head)
            if hlen > 1 << 24:
                raise Damage(f"implausible record header length at byte {fh.tell() - 4}")
            at = fh.tell() - 4
            header = _ros1_fields(_read_exact(fh, hlen, "record header"))
            (dlen,) = struct.unpack("<I", _read_exact(fh, 4, "record"))
            try:
                op = _ros1_op(header)
                if op == b"\x05":  # chunk: decode what is there, even when cut off
                    yield from _ros1_chunk(fh, header, dlen, seen)
                elif op in ROS1_CHUNK_OPS:
                    yield from _ros1_inner(header, _read_exact(fh, dlen, "record"), seen)
                else:  # bag header, index data, chunk info: skip
                    fh.seek(dlen, 1)
            except Damage as err:
                raise Damage(f"{err} (record at byte {at})") from None


# ---------------------------------------------------------------------------- MCAP


class _Buf:
    def __init__(self, data: bytes):
        self.data = data
        self.pos = 0

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise Damage("MCAP record content cut off")
        b = self.data[self.pos : self.pos + n]
        self.pos += n
        return b

    def u16(self) -> int:
        return int(struct.unpack("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack("<Q", self.take(8))[0])

    def string(self) -> str:
        return self.take(self.u32()).decode()


def _mcap_records(data: bytes) -> Iterator[tuple[int, bytes]]:
    pos = 0
    while pos < len(data):
        if pos + 9 > len(data):
            raise Damage("MCAP chunk record cut off")
        op = data[pos]
        (n,) = struct.unpack_from("<Q", data, pos + 1)
        if pos + 9 + n > len(data):
            raise Damage("MCAP chunk record cut off")
        yield op, data[pos + 9 : pos + 9 + n]
        pos += 9 + n


def _mcap_decompress(kind: str, data: bytes) -> bytes:
    if kind == "":
        return data
    if kind == "lz4":
        import lz4.frame

        try:
            return lz4.frame.decompress(data)
        except RuntimeError as err:
            raise Damage(f"lz4 chunk cannot be decompressed: {err}") from None
    if kind == "zstd":
        try:
            from backports import zstd
        except ImportError:  # Python >= 3.14
            from compression import zstd  # type: ignore[no-redef]
        try:
            return bytes(zstd.decompress(data))
        except Exception as err:  # the zstd module's own error type
            raise Damage(f"zstd chunk cannot be decompressed: {err}") from None
    raise Damage(f"unknown MCAP chunk compression '{kind}'")


class _McapState:
    def __init__(self) -> None:
        self.schemas: dict[int, tuple[str, str, str]] = {}  # id -> name, encoding, data
        self.channels: set[int] = set()

    def handle(self, op: int, content: bytes, cut: bool = False) -> Iterator[SalvageRecord]:
        """Records of one top-level record; ``cut``: the content is cut off (a chunk yields what it has)."""
        b = _Buf(content)
        if op == 0x03:  # schema
            sid = b.u16()
            name, enc = b.string(), b.string()
            self.schemas[sid] = (name, enc, b.take(b.u32()).decode(errors="replace"))
        elif op == 0x04:  # channel
            cid, sid = b.u16(), b.u16()
            topic = b.string()
            if cid in self.channels:
                return
            self.channels.add(cid)
            name, enc, text = self.schemas.get(sid, ("", "", ""))
            fmt = {"ros2msg": "msg", "ros1msg": "msg", "ros2idl": "idl"}.get(enc, "")
            yield SalvageConnection(cid, topic, name, text, fmt)
        elif op == 0x05:  # message
            cid = b.u16()
            b.u32()  # sequence
            log_time = b.u64()
            b.u64()  # publish time
            yield SalvageMessage(cid, log_time, content[b.pos :])
        elif op == 0x06:  # chunk
            b.u64()
            b.u64()  # start/end time
            b.u64()  # uncompressed size
            b.u32()  # crc
            kind = b.string()
            n = b.u64()
            if cut:
                if kind != "":
                    raise Damage(f"compressed ({kind}) MCAP chunk cut off")
                records = content[b.pos : b.pos + n]
            else:
                records = b.take(n)
            for op2, c2 in _mcap_records(_mcap_decompress(kind, records)):
                yield from self.handle(op2, c2)
        if cut:
            raise Damage("MCAP record cut off at the end of the file")


def scan_mcap(path: Path) -> Iterator[SalvageRecord]:
    """Channels and messages of an MCAP file in file order, up to the first damaged record."""
    state = _McapState()
    with open(path, "rb") as fh:
        if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise Damage("not an MCAP file (bad magic)")
        while True:
            head = fh.read(9)
            if not head:
                return
            if len(head) < 9:
                raise Damage(f"record cut off at byte {fh.tell()}")
            op = head[0]
            (n,) = struct.unpack_from("<Q", head, 1)
            if op == 0x02:  # footer: the data section is over
                return
            if op in (0x03, 0x04, 0x05, 0x06):
                content = fh.read(n)
                yield from state.handle(op, content, cut=len(content) < n)
            else:
                fh.seek(n, 1)
                if fh.tell() > path.stat().st_size:
                    raise Damage("record cut off at the end of the file")


# ---------------------------------------------------------------------------- SQLite (ROS 2 .db3)


def _sqlite_cut_page(path: Path) -> tuple[str, int | None]:
    """How the file falls short of its header's page count, and the number of its cut-off last page.

    SQLite reads a cut-off page as if its missing bytes were zeros, so rows stored on it (or data
    running into it) come back silently zeroed. None when the file ends on a page boundary.
    """
    with open(path, "rb") as fh:
        head = fh.read(100)
        size = fh.seek(0, 2)
    if len(head) < 100 or not head.startswith(b"SQLite format 3\0"):
        raise Damage("not an SQLite database (bad header)")
    page = struct.unpack_from(">H", head, 16)[0]
    page = 65536 if page == 1 else page
    pages = struct.unpack_from(">I", head, 28)[0]
    note = f"the file holds {size / page:.1f} of its {pages} pages" if size < pages * page else ""
    return note, (size // page + 1 if size % page else None)


def _sqlite_first_row_on(con: sqlite3.Connection, page_no: int) -> int | None:
    """Position (in rowid order) of the first message row with content on page ``page_no``.

    Walks the messages table's pages with SQLite's ``dbstat`` table (leaves in rowid order, each
    followed by its cells' overflow pages, named ``<leaf path><cell>+<n>``). None when no row is
    stored there or ``dbstat`` is missing from this SQLite build; the rows walked so far when the
    walk stops at a malformed page.
    """
    first = 0  # position of the current leaf's first row
    count = 0
    try:
        con.execute("SELECT 1 FROM dbstat LIMIT 0")
    except sqlite3.Error:
        return None
    try:
        for pageno, path, kind, ncell in con.execute(
                "SELECT pageno, path, pagetype, ncell FROM dbstat WHERE name = 'messages'"):
            if kind == "leaf":
                first, count = count, count + int(ncell)
                if pageno == page_no:
                    return first
            elif kind == "overflow" and pageno == page_no:
                return first + int(str(path).rsplit("/", 1)[-1].split("+")[0], 16)
    except sqlite3.Error:  # the walk itself hit a malformed page: trust no row from here on
        return count
    return None


def _sqlite_connect(path: Path) -> sqlite3.Connection:
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
        # Lenient: a file shorter than its header's page count opens (SQLite refuses it otherwise)
        # and its pages are read until the first missing one. Read-only, so nothing is written.
        con.execute("PRAGMA writable_schema = ON")
    except sqlite3.Error as err:
        raise Damage(f"SQLite cannot open the database: {err}") from None
    return con


def _sqlite_topics(con: sqlite3.Connection) -> Iterator[SalvageConnection]:
    try:
        topics = con.execute("SELECT id, name, type FROM topics").fetchall()
        defs: dict[str, tuple[str, str]] = {}
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "message_definitions" in tables:
            for typ, enc, text in con.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"):
                defs[typ] = ({"ros2msg": "msg", "ros2idl": "idl"}.get(enc, ""), text)
    except sqlite3.Error as err:
        raise Damage(f"SQLite cannot read the topic table: {err}") from None
    for tid, name, typ in topics:
        fmt, text = defs.get(typ, ("", ""))
        yield SalvageConnection(int(tid), name, typ, text if fmt else "", fmt)


def scan_sqlite(path: Path) -> Iterator[SalvageRecord]:
    """Topics, then messages in insertion order, up to the first row SQLite cannot read.

    A file cut off in the middle (shorter than its header says) is read up to its first missing
    page; a message that runs into a cut-off last page is not returned (its end would be zeros).
    """
    note, cut_page = _sqlite_cut_page(path)
    where = f" ({note})" if note else ""
    con = _sqlite_connect(path)
    try:
        conns = list(_sqlite_topics(con))
        topics = {c.cid for c in conns}
        yield from conns
        stop = _sqlite_first_row_on(con, cut_page) if cut_page is not None else None
        n = 0
        try:
            for tid, t, data in con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY rowid"):
                if not isinstance(data, bytes) or not isinstance(t, int) or tid not in topics:
                    raise Damage(f"message {n + 1} is a malformed row (topic id {tid!r}){where}")
                if n == stop:
                    raise Damage(f"message {n + 1} runs into the cut-off end of the file{where}")
                yield SalvageMessage(tid, t, data)
                n += 1
        except sqlite3.Error as err:
            raise Damage(f"SQLite stopped at a damaged page after {n} messages: {err}{where}") from None
    finally:
        con.close()
