"""Recordings: rosbag2 (mcap, sqlite3) and ROS 1 bags with the artrack message types.

ROS-free: rosbags + numpy + OpenCV. Messages are rosbags' pure-Python message
objects (build them with :mod:`artrack.messages` and ``rosbags_factory()``).

Bag paths (what ``--out`` / ``INPUT`` mean everywhere)
------------------------------------------------------
Writing (:class:`BagWriter`, :func:`write_scene_bag`) picks the layout from the path:

* ``scene.mcap`` — ONE self-contained MCAP file (rosbag2 mcap storage: profile
  ``ros2``, ``ros2msg`` schemas with every definition, custom artrack types
  included, and the rosbag2 metadata record). Opens with ``ros2 bag info/play
  scene.mcap``, Foxglove, the ``mcap`` CLI and rosbags; no ``metadata.yaml`` needed.
* ``scene.db3`` — one sqlite3 storage file (rosbag2 schema 4, definitions inside).
* any other path, e.g. ``out/track`` — a rosbag2 DIRECTORY ``track/`` holding
  ``metadata.yaml`` and ``track.mcap`` (``storage="sqlite3"``: ``track.db3``),
  exactly what ``ros2 bag record -o track`` makes.

Writing goes to a hidden temporary sibling (``.scene.mcap.XXXX.tmp/``) that is
moved into place only when the writer closes without an error, so a failed or
interrupted run leaves nothing at the target (an existing bag there is replaced
only on success; an existing directory that is not a bag is never touched).

Reading (:func:`open_bag`, :func:`read_scene`) accepts all of the above plus a
rosbag2 directory of either storage, a directory holding only ``.mcap`` files
(no ``metadata.yaml``) and a ROS 1 ``.bag`` file.

Times: every stamp is an integer in nanoseconds. ``BagReader.messages`` yields
the bag's log time (when the message was recorded); image and scene helpers
use the ``header.stamp`` of the messages.

Truncated MCAP files (copy interrupted, disk full, recorder killed) raise
:class:`~artrack.errors.BagError` saying how many messages are readable and
which record is incomplete; ``open_bag(path, allow_truncated=True)`` instead
reads every message before the damage (in file order) and sets
``reader.truncated``. sqlite3 and ROS 1 bags have no such recovery (error only).

Scene layout (``artrack synth``; the live graph uses the same topics)
---------------------------------------------------------------------
per camera ``<name>``:
  ``/cameras/<name>/image_raw``  sensor_msgs/Image bgr8, header.frame_id ``<name>_optical_frame``
  (or sensor_msgs/CompressedImage on ``/cameras/<name>/image_raw/compressed``);
  ``/cameras/<name>/camera_info``  sensor_msgs/CameraInfo (plumb_bob, P = K [I|0]), every frame;
  ``/cameras/<name>/extrinsics``  geometry_msgs/TransformStamped world -> optical frame
  (world_from_camera), once at the start, transient-local QoS;
``/artrack/ground_truth``  artrack_msgs/TrackedBody (joint_names + joints, world frame, m).
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import shutil
import struct
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from .cameras import Camera
from .config import parse_yaml, yaml_error_text
from .errors import BagError, CalibrationError, InputError, check_output_path

__all__ = [
    "GROUND_TRUTH_TOPIC",
    "BagReader",
    "BagWriter",
    "JointTrack",
    "Scene",
    "camera_topic",
    "find_msgs_dir",
    "image_from_msg",
    "open_bag",
    "read_body_topic",
    "read_scene",
    "typestore",
    "write_scene_bag",
]

GROUND_TRUTH_TOPIC = "/artrack/ground_truth"
WORLD_FRAME = "world"
_MSG_PKG = "artrack_msgs"


def camera_topic(camera: str, leaf: str) -> str:
    """``/cameras/<camera>/<leaf>`` (leaf: image_raw, camera_info, extrinsics, blobs, ...)."""
    return f"/cameras/{camera}/{leaf}"


# =========================================================================== typestore
def find_msgs_dir() -> Path:
    """Directory holding the artrack_msgs ``*.msg`` files.

    Looked up in order: ``$ARTRACK_MSGS_DIR``; walking up from this file, the sibling source
    package (``src/artrack_msgs/msg``, so a source checkout uses its own definitions), an
    isolated colcon install (``install/artrack_msgs/share/artrack_msgs/msg``) or a merged one
    (``share/artrack_msgs/msg``); finally ``share/artrack_msgs/msg`` under ``$AMENT_PREFIX_PATH``.
    """
    env = os.environ.get("ARTRACK_MSGS_DIR")
    if env:
        d = Path(env)
        if not any(d.glob("*.msg")):
            raise BagError(f"ARTRACK_MSGS_DIR={env}: no .msg files there")
        return d
    candidates = []
    for parent in Path(__file__).resolve().parents:
        candidates += [
            parent / _MSG_PKG / "msg",
            parent / _MSG_PKG / "share" / _MSG_PKG / "msg",
            parent / "share" / _MSG_PKG / "msg",
        ]
    candidates += [
        Path(p) / "share" / _MSG_PKG / "msg" for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":") if p
    ]
    for d in candidates:
        if d.is_dir() and any(d.glob("*.msg")):
            return d
    raise BagError(f"cannot find the {_MSG_PKG} .msg files (set ARTRACK_MSGS_DIR)")


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """rosbags Typestore: ROS 2 Jazzy types plus ``artrack_msgs/msg/*`` from the .msg files (cached)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for f in sorted(find_msgs_dir().glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"{_MSG_PKG}/msg/{f.stem}"))
    store.register(types)
    return store


def _store_from_definitions(defs: Iterable[tuple[str, str, str]], fallback: Typestore) -> Typestore:
    """Typestore from a bag's own definitions ``(msgtype, 'msg'|'idl', text)`` (as rosbags' AnyReader);
    ``fallback`` when the bag carries none."""
    types: dict = {}
    for msgtype, fmt, text in defs:
        if fmt == "msg":
            types.update(get_types_from_msg(text, msgtype))
        elif fmt == "idl":
            sep = "=" * 80 + "\n"
            if text.startswith(f"{sep}IDL: "):
                for part in text.split(sep)[1:]:
                    types.update(get_types_from_idl(part.split("\n", 1)[1]))
            else:
                types.update(get_types_from_idl(text))
    if not types:
        return fallback
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


# =========================================================================== QoS
_T0 = QosTime(0, 0)


def _qos(depth: int, reliability: QosReliability, durability: QosDurability) -> Qos:
    return Qos(
        QosHistory.KEEP_LAST, depth, reliability, durability, _T0, _T0, QosLiveliness.AUTOMATIC, _T0, False
    )


#: Named offered-QoS profiles for :meth:`BagWriter.add_topic` (what ``ros2 bag play`` re-offers).
QOS_PROFILES: dict[str, list[Qos]] = {
    "reliable": [_qos(10, QosReliability.RELIABLE, QosDurability.VOLATILE)],
    "latched": [_qos(1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL)],
    "sensor": [_qos(5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE)],
}


# =========================================================================== writing
def looks_like_bag_dir(d: Path) -> bool:
    """A rosbag2 directory (has metadata.yaml), or one holding only storage files (or nothing)."""
    if (d / "metadata.yaml").is_file():
        return True
    return all(e.is_file() and e.suffix in (".mcap", ".db3") for e in d.iterdir())


class BagWriter:
    """Writes a rosbag2 recording; a context manager (see the module docstring for the path layout).

    ``path`` ending in ``.mcap`` / ``.db3``: a single storage file; otherwise a rosbag2
    directory with ``storage`` ``"mcap"`` (default) or ``"sqlite3"``. rosbag2 format
    version 9. ``compression=True`` zstd-compresses the MCAP chunks. Nothing appears at
    ``path`` until :meth:`close` (or a clean ``with`` exit); an exception aborts and
    removes the temporary output. ``overwrite=False`` refuses an existing target.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        storage: str | None = None,
        compression: bool = False,
        overwrite: bool = True,
    ):
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        self.single_file = suffix in (".mcap", ".db3")
        implied = {".mcap": "mcap", ".db3": "sqlite3"}.get(suffix)
        if storage is None:
            storage = implied or "mcap"
        if storage not in ("mcap", "sqlite3"):
            raise ValueError(f"{self.path}: storage must be 'mcap' or 'sqlite3', got {storage!r}")
        if implied and storage != implied:
            raise ValueError(f"{self.path}: suffix {suffix} contradicts storage={storage!r}")
        if compression and storage != "mcap":
            raise ValueError(f"{self.path}: compression is only supported for mcap storage")
        self.storage = storage
        self.compression = compression
        self.overwrite = overwrite
        self.count = 0
        self._writer: Writer | None = None
        self._tmp: Path | None = None
        self._inner: Path | None = None
        self._conns: dict[str, Any] = {}
        self._types: dict[str, str] = {}

    # ------------------------------------------------------------- lifecycle
    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    def open(self) -> None:
        """Start writing into the temporary sibling directory."""
        p = self.path
        if p.exists() or p.is_symlink():
            if not self.overwrite:
                raise BagError(f"{p}: exists already (overwrite=False)")
            if self.single_file and p.is_dir():
                raise BagError(f"{p}: is a directory, cannot write a {p.suffix} file there")
            if not self.single_file and (not p.is_dir() or not looks_like_bag_dir(p)):
                raise BagError(f"{p}: exists and is not a rosbag2 directory; not overwriting")
        check_output_path(p)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent))
        except OSError as exc:
            raise BagError(f"{p}: cannot create output ({exc.strerror})") from None
        self._inner = self._tmp / (p.stem if self.single_file else p.name)
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._inner, version=9, storage_plugin=plugin)
        if self.compression:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            self._writer.open()
        except Exception as exc:
            self.abort()
            raise BagError(f"{p}: cannot open for writing ({exc})") from None

    def close(self) -> None:
        """Finish the bag (index, metadata) and move it into place."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        try:
            writer.close()
            assert self._inner is not None
            if self.single_file:
                ext = ".mcap" if self.storage == "mcap" else ".db3"
                os.replace(self._inner / f"{self._inner.name}{ext}", self.path)
            else:
                old = None
                if self.path.exists():
                    old = self._tmp / ".old"
                    os.rename(self.path, old)
                os.rename(self._inner, self.path)
        except OSError as exc:
            raise BagError(f"{self.path}: cannot finish the bag ({exc})") from None
        finally:
            self._cleanup()

    def abort(self) -> None:
        """Drop everything written so far (the target is left as it was)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            with contextlib.suppress(Exception):  # best effort: the directory goes anyway
                writer.abort()
        self._cleanup()

    def _cleanup(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    # ------------------------------------------------------------- topics
    def add_topic(self, topic: str, msgtype: str, qos: str | Sequence[Qos] | None = None) -> None:
        """Register ``topic`` with type ``msgtype`` (e.g. ``"sensor_msgs/msg/Image"``).

        qos: offered QoS recorded in the bag: ``None``/``"reliable"``, ``"latched"``
        (transient local, depth 1), ``"sensor"`` (best effort) or a list of rosbags ``Qos``.
        Adding the same topic again with the same type is a no-op. May be called at any
        time while open (the live recorder adds topics as they appear).
        """
        if self._writer is None:
            raise BagError(f"{self.path}: writer is not open")
        if topic in self._types:
            if self._types[topic] != msgtype:
                raise BagError(
                    f"{self.path}: topic '{topic}' already has type {self._types[topic]}, not {msgtype}"
                )
            return
        store = typestore()
        if msgtype not in store.types:
            raise BagError(f"{self.path}: topic '{topic}': unknown message type '{msgtype}'")
        profiles = (
            QOS_PROFILES["reliable"] if qos is None else (QOS_PROFILES[qos] if isinstance(qos, str) else qos)
        )
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=store, offered_qos_profiles=list(profiles)
        )
        self._types[topic] = msgtype

    def topics(self) -> dict[str, str]:
        """topic -> message type of every registered topic."""
        return dict(self._types)

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a rosbags message object) as CDR and write it at log time ``stamp_ns``.

        An unregistered topic is added with the message's own type (``msg.__msgtype__``).
        """
        if topic not in self._types:
            msgtype = getattr(msg, "__msgtype__", None)
            if msgtype is None:
                raise BagError(
                    f"{self.path}: topic '{topic}' was not added (add_topic) and the message has no type"
                )
            self.add_topic(topic, msgtype)
        try:
            data = typestore().serialize_cdr(msg, self._types[topic])
        except Exception as exc:
            raise BagError(
                f"{self.path}: topic '{topic}': cannot serialise message as {self._types[topic]} ({exc})"
            ) from None
        self.write_raw(topic, stamp_ns, data)

    def write_raw(self, topic: str, stamp_ns: int, data: bytes | memoryview) -> None:
        """Write serialised CDR bytes (with the 4-byte encapsulation header) at log time ``stamp_ns``."""
        if self._writer is None:
            raise BagError(f"{self.path}: writer is not open")
        conn = self._conns.get(topic)
        if conn is None:
            raise BagError(f"{self.path}: topic '{topic}' was not added (add_topic)")
        self._writer.write(conn, int(stamp_ns), data)
        self.count += 1


# =========================================================================== MCAP recovery scan
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_NAMES = {
    0x01: "header",
    0x02: "footer",
    0x03: "schema",
    0x04: "channel",
    0x05: "message",
    0x06: "chunk",
    0x07: "message index",
    0x08: "chunk index",
    0x09: "attachment",
    0x0A: "attachment index",
    0x0B: "statistics",
    0x0C: "metadata",
    0x0D: "metadata index",
    0x0E: "summary offset",
    0x0F: "data end",
}


@dataclass
class _McapScan:
    """State of a sequential MCAP scan (ids are per file)."""

    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)  # id -> (name, encoding, text)
    channels: dict[int, tuple[str, int, str]] = field(
        default_factory=dict
    )  # id -> (topic, schema id, encoding)
    counts: dict[int, int] = field(default_factory=dict)  # channel id -> readable messages
    n_messages: int = 0
    problem: str | None = None  # None: the file is complete
    not_mcap: bool = False  # bad magic: nothing is readable
    data_complete: bool = False  # every message is readable (damage only in the summary)


def _read_str(buf: memoryview, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, off)
    off += 4
    if off + n > len(buf):
        raise ValueError("string runs past its record")
    return bytes(buf[off : off + n]).decode(), off + n


def _parse_records(buf: memoryview, scan: _McapScan, out: list | None) -> None:
    """Schema / channel / message records of a chunk body (or a single top-level record)."""
    off = 0
    while off < len(buf):
        if off + 9 > len(buf):
            raise ValueError("record header runs past the end")
        op = buf[off]
        (length,) = struct.unpack_from("<Q", buf, off + 1)
        body = buf[off + 9 : off + 9 + length]
        if len(body) != length:
            raise ValueError(f"{_OP_NAMES.get(op, 'record')} runs past the end")
        _parse_record(op, body, scan, out)
        off += 9 + length


def _parse_record(op: int, body: memoryview, scan: _McapScan, out: list | None) -> None:
    if op == 0x03:
        (sid,) = struct.unpack_from("<H", body, 0)
        name, o = _read_str(body, 2)
        enc, o = _read_str(body, o)
        (n,) = struct.unpack_from("<I", body, o)
        scan.schemas[sid] = (name, enc, bytes(body[o + 4 : o + 4 + n]).decode())
    elif op == 0x04:
        cid, sid = struct.unpack_from("<HH", body, 0)
        topic, o = _read_str(body, 4)
        enc, o = _read_str(body, o)
        scan.channels[cid] = (topic, sid, enc)
    elif op == 0x05:
        cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
        if cid not in scan.channels:
            raise ValueError(f"message on unknown channel {cid}")
        scan.counts[cid] = scan.counts.get(cid, 0) + 1
        scan.n_messages += 1
        if out is not None:
            out.append((log_time, cid, bytes(body[22:])))


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == "":
        raw = data
    elif compression == "zstd":
        try:
            from compression import zstd  # Python >= 3.14
        except ImportError:
            from backports import zstd
        raw = zstd.decompress(data)
    elif compression == "lz4":
        import lz4.frame

        raw = lz4.frame.decompress(data)
    else:
        raise ValueError(f"unsupported chunk compression '{compression}'")
    if len(raw) != size:
        raise ValueError(f"chunk decompresses to {len(raw)} bytes, header says {size}")
    return raw


def _scan_mcap(path: Path, scan: _McapScan, keep: bool) -> Iterator[tuple[int, int, bytes]]:
    """Walk an MCAP file record by record; yields (log_time, channel id, cdr) when ``keep``.

    Stops at the first incomplete or undecodable record, describing it in ``scan.problem``.
    Messages of one chunk are yielded in log-time order, chunks in file order.
    """
    size = path.stat().st_size
    with path.open("rb") as f:
        if f.read(8) != _MCAP_MAGIC:
            scan.problem = "not an MCAP file (bad magic at offset 0)"
            scan.not_mcap = True
            return
        pos = 8
        while True:
            head = f.read(9)
            if len(head) < 9:
                where = "the file ends" if not head else f"record header at offset {pos} is incomplete"
                scan.problem = f"truncated after {scan.n_messages} messages ({where} before the MCAP footer)"
                return
            op = head[0]
            (length,) = struct.unpack_from("<Q", head, 1)
            kind = _OP_NAMES.get(op, f"record 0x{op:02x}")
            if pos + 9 + length > size:
                scan.problem = (
                    f"truncated after {scan.n_messages} messages ({kind} at offset {pos} is incomplete: "
                    f"{size - pos - 9} of {length} bytes present)"
                )
                return
            body = memoryview(f.read(length))
            out: list | None = [] if keep else None
            try:
                if op == 0x06:
                    _start, _end, usize, _crc = struct.unpack_from("<QQQI", body, 0)
                    compression, o = _read_str(body, 28)
                    (csize,) = struct.unpack_from("<Q", body, o)
                    data = bytes(body[o + 8 : o + 8 + csize])
                    if len(data) != csize:
                        raise ValueError("compressed data runs past the chunk")
                    _parse_records(memoryview(_decompress(data, compression, usize)), scan, out)
                elif op in (0x03, 0x04, 0x05):
                    _parse_record(op, body, scan, out)
                elif op == 0x0F:
                    scan.data_complete = True
                elif op == 0x02:
                    if f.read(8) != _MCAP_MAGIC:
                        scan.problem = (
                            f"truncated in the closing magic (all {scan.n_messages} messages readable)"
                        )
                    return
            except (ValueError, struct.error, UnicodeDecodeError) as exc:
                scan.problem = f"corrupt after {scan.n_messages} messages ({kind} at offset {pos}: {exc})"
                return
            if out:
                out.sort(key=lambda m: m[0])
                yield from out
            pos += 9 + length


def _describe(scan: _McapScan) -> str:
    if scan.problem and scan.data_complete and scan.problem.startswith("truncated after"):
        return scan.problem.replace("truncated after", "truncated in the summary section after", 1)
    return scan.problem or "complete"


# =========================================================================== reading
class JointTrack(NamedTuple):
    """Joint positions over time: stamps (T,) int64 ns, joint_names (J,), joints (T, J, 3) m, world frame."""

    stamps: np.ndarray
    joint_names: list[str]
    joints: np.ndarray


def _ns(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _header_stamp(msg: Any) -> int:
    return _ns(msg.header.stamp)


def image_from_msg(msg: Any, where: str = "image") -> np.ndarray:
    """(H, W, 3) uint8 BGR from a sensor_msgs/Image (bgr8, rgb8, mono8, bgra8, rgba8) or
    sensor_msgs/CompressedImage (anything cv2.imdecode reads). BagError names ``where``."""
    if hasattr(msg, "format"):  # CompressedImage
        data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        if img is None:
            raise BagError(
                f"{where}: cannot decode compressed image (format '{msg.format}', {data.size} bytes)"
            )
        return img
    from .messages import bgr_from_image_msg

    try:
        return bgr_from_image_msg(msg, where)
    except ValueError as exc:
        raise BagError(str(exc)) from None


class BagReader:
    """An open recording (use :func:`open_bag`). Context manager; :meth:`close` when done.

    ``truncated``: the bag is damaged and only the messages before the damage are read
    (``problem`` says what is wrong). Message objects come from the bag's own embedded
    definitions (the authoritative wire format) or, when it has none, from :func:`typestore`.
    """

    def __init__(self, path: str | os.PathLike, allow_truncated: bool = False):
        self.path = Path(path)
        self.truncated = False
        self.problem: str | None = None
        self._any: AnyReader | None = None
        self._files: list[Path] = []  # MCAP files read by the recovery scan
        self._topics: dict[str, str] = {}
        self._counts: dict[str, int] = {}
        self._order: list[str] = []
        self._store: Typestore | None = None
        p = self.path
        if not p.exists():
            raise BagError(f"{p}: no such bag (file or rosbag2 directory)")
        if p.is_file() and p.suffix.lower() not in (".mcap", ".db3", ".bag"):
            raise BagError(f"{p}: unknown bag format (expected .mcap, .db3, .bag or a rosbag2 directory)")
        if p.is_dir() and (p / "metadata.yaml").exists():
            _check_metadata(p / "metadata.yaml")
        mcaps = self._mcap_files()
        sources = [p]
        if p.is_dir() and not (p / "metadata.yaml").exists():
            if not mcaps:
                raise BagError(f"{p}: not a bag directory (no metadata.yaml and no .mcap files)")
            sources = mcaps  # e.g. a recording whose metadata.yaml was lost: read the storage files
        try:
            reader = AnyReader(sources, default_typestore=typestore())
            reader.open()
        except Exception as exc:
            if not mcaps:
                raise BagError(f"{p}: cannot read bag ({_short(exc)})") from None
            self._recover(mcaps, allow_truncated, _short(exc))
            return
        self._any = reader
        for c in reader.connections:
            self._topics.setdefault(c.topic, c.msgtype)
            self._counts[c.topic] = self._counts.get(c.topic, 0) + c.msgcount
            if c.topic not in self._order:
                self._order.append(c.topic)

    def _mcap_files(self) -> list[Path]:
        p = self.path
        if p.is_file():
            return [p] if p.suffix.lower() == ".mcap" else []
        meta = p / "metadata.yaml"
        if meta.exists():
            try:
                info = parse_yaml(meta.read_text())["rosbag2_bagfile_information"]
                if info.get("storage_identifier") != "mcap":
                    return []
                if info.get("compression_mode") and str(info.get("compression_mode")).lower() != "none":
                    return []
                return [p / Path(x).name for x in info["relative_file_paths"] if (p / Path(x).name).is_file()]
            except Exception:
                return []
        return sorted(x for x in p.iterdir() if x.suffix == ".mcap" and x.is_file())

    def _recover(self, files: list[Path], allow_truncated: bool, reason: str) -> None:
        """Sequential scan of the MCAP files: find what is readable and what is wrong."""
        problems, defs, total, fatal = [], {}, 0, False
        for f in files:
            scan = _McapScan()
            for _ in _scan_mcap(f, scan, keep=False):
                pass
            total += scan.n_messages
            fatal |= scan.not_mcap
            if scan.problem:
                name = f.name if f != self.path else ""
                problems.append((name + ": " if name else "") + _describe(scan))
            for cid, (topic, sid, _enc) in scan.channels.items():
                sname, senc, stext = scan.schemas.get(sid, (None, "", ""))
                if sname is None:
                    continue
                self._topics.setdefault(topic, sname)
                if topic not in self._order:
                    self._order.append(topic)
                self._counts[topic] = self._counts.get(topic, 0) + scan.counts.get(cid, 0)
                fmt = {"ros2msg": "msg", "ros2idl": "idl", "omgidl": "idl"}.get(senc)
                if fmt:
                    defs[sname] = (sname, fmt, stext)
        if not problems:
            # The scan finds nothing wrong: report what rosbags did not like.
            raise BagError(f"{self.path}: cannot read bag ({reason})")
        self.problem = "; ".join(problems)
        if not allow_truncated or fatal:
            if fatal:
                hint = ""
            elif total == 0:
                hint = "; no message is readable"
            else:
                hint = (f"; the {total} messages before it can be read with allow_truncated "
                        "(artrack track --allow-truncated)")
            raise BagError(f"{self.path}: {self.problem}{hint}")
        self.truncated = True
        self._files = files
        try:
            self._store = _store_from_definitions(defs.values(), typestore())
        except Exception as exc:
            raise BagError(f"{self.path}: bad message definitions in the bag ({_short(exc)})") from None

    # ----------------------------------------------------------------- API
    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def close(self) -> None:
        if self._any is not None:
            try:
                self._any.close()
            finally:
                self._any = None

    def topics(self) -> dict[str, str]:
        """topic -> message type, in the order the bag declares them."""
        return {t: self._topics[t] for t in self._order}

    def message_counts(self) -> dict[str, int]:
        """topic -> number of (readable) messages."""
        return {t: self._counts.get(t, 0) for t in self._order}

    def _check_topics(self, topics: Iterable[str] | None) -> list[str] | None:
        if topics is None:
            return None
        topics = [topics] if isinstance(topics, str) else list(topics)
        for t in topics:
            if t not in self._topics:
                have = ", ".join(self._order[:8]) + (", ..." if len(self._order) > 8 else "")
                raise BagError(f"{self.path}: no topic '{t}' in the bag (has: {have or 'none'})")
        return topics

    def messages(
        self, topics: Iterable[str] | None = None, *, raw: bool = False
    ) -> Iterator[tuple[str, int, Any]]:
        """Yield ``(topic, log_time_ns, msg)`` for ``topics`` (default: all), in log-time order
        (file order for a truncated bag). ``raw=True`` yields the serialised bytes instead.
        A topic not in the bag raises BagError naming it; damage met while reading raises BagError
        saying how many messages were read."""
        wanted = self._check_topics(topics)
        n = 0
        if self._any is not None:
            reader = self._any
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            if not conns:
                return
            it = reader.messages(connections=conns)
            while True:
                try:
                    item = next(it, None)
                    if item is None:
                        return
                    conn, t, data = item
                    msg = data if raw else reader.deserialize(data, conn.msgtype)
                except BagError:
                    raise
                except Exception as exc:
                    raise BagError(f"{self.path}: corrupt after {n} messages ({_short(exc)})") from None
                n += 1
                yield conn.topic, t, msg
        else:
            assert self._store is not None
            for f in self._files:
                scan = _McapScan()
                for t, cid, data in _scan_mcap(f, scan, keep=True):
                    topic, sid, _ = scan.channels[cid]
                    if wanted is not None and topic not in wanted:
                        continue
                    if raw:
                        yield topic, t, data
                        continue
                    msgtype = scan.schemas[sid][0]
                    try:
                        msg = self._store.deserialize_cdr(data, msgtype)
                    except Exception as exc:
                        raise BagError(
                            f"{self.path}: topic '{topic}': cannot decode message ({_short(exc)})"
                        ) from None
                    yield topic, t, msg

    def images(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, np.ndarray]]:
        """Yield ``(topic, header_stamp_ns, image (H, W, 3) uint8 BGR)`` from sensor_msgs/Image and
        CompressedImage topics (default: every image topic in the bag)."""
        if topics is None:
            topics = [t for t, ty in self.topics().items() if ty.endswith(("/Image", "/CompressedImage"))]
        for topic, _, msg in self.messages(topics):
            yield topic, _header_stamp(msg), image_from_msg(msg, f"{self.path}: topic '{topic}'")


#: Keys of ``rosbag2_bagfile_information`` that rosbags needs to open a rosbag2 directory.
_METADATA_KEYS = ("version", "storage_identifier", "relative_file_paths", "topics_with_message_count",
                  "duration", "starting_time", "message_count")


def _check_metadata(meta: Path) -> None:
    """BagError naming ``meta`` (a rosbag2 metadata.yaml) and the field, if it cannot describe a bag."""
    try:
        data = parse_yaml(meta.read_text())
    except OSError as exc:
        raise BagError(f"{meta}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise BagError(f"{meta}: not a text file") from None
    except yaml.YAMLError as exc:
        raise BagError(f"{meta}: not valid YAML ({yaml_error_text(exc)})") from None
    top = "rosbag2_bagfile_information"
    info = data.get(top) if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise BagError(f"{meta}: no field '{top}' (not rosbag2 metadata)")
    for key in _METADATA_KEYS:
        if info.get(key) is None:
            raise BagError(f"{meta}: no field '{top}.{key}'")
    files = info["relative_file_paths"]
    if not isinstance(files, list) or not files:
        raise BagError(f"{meta}: field '{top}.relative_file_paths' must be a non-empty list")
    for name in files:
        if not (meta.parent / Path(str(name)).name).is_file():
            raise BagError(f"{meta}: field '{top}.relative_file_paths' names '{name}', which is missing")
    topics = info["topics_with_message_count"]
    if not isinstance(topics, list):
        raise BagError(f"{meta}: field '{top}.topics_with_message_count' must be a list")
    for i, entry in enumerate(topics):
        tm = entry.get("topic_metadata") if isinstance(entry, dict) else None
        for key in ("name", "type", "serialization_format"):
            if not isinstance(tm, dict) or tm.get(key) is None:
                raise BagError(f"{meta}: no field '{top}.topics_with_message_count[{i}].topic_metadata.{key}'")


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 300 else text[:297] + "..."


def open_bag(path: str | os.PathLike, allow_truncated: bool = False) -> BagReader:
    """Open a recording for reading: a rosbag2 directory (mcap or sqlite3), a ``.mcap`` or
    ``.db3`` storage file, a directory of ``.mcap`` files, or a ROS 1 ``.bag``.

    A truncated/corrupt MCAP raises BagError naming the file, the number of readable messages
    and the incomplete record; with ``allow_truncated=True`` the readable messages are served
    and ``reader.truncated`` is True.
    """
    return BagReader(path, allow_truncated=allow_truncated)


def read_body_topic(
    path: str | os.PathLike, topic: str = GROUND_TRUTH_TOPIC, allow_truncated: bool = False
) -> JointTrack:
    """Joints of every artrack_msgs/TrackedBody on ``topic`` (stamps from header.stamp, sorted).

    Raises BagError if the topic is missing, empty or its joint names change."""
    stamps, rows, names = [], [], None
    with open_bag(path, allow_truncated=allow_truncated) as bag:
        for _, _, msg in bag.messages([topic]):
            n = list(msg.joint_names)
            if names is None:
                names = n
            elif n != names:
                raise BagError(f"{path}: topic '{topic}': joint_names change at stamp {_header_stamp(msg)}")
            pts = np.array([[p.x, p.y, p.z] for p in msg.joints], dtype=np.float64).reshape(-1, 3)
            if pts.shape[0] != len(names):
                raise BagError(f"{path}: topic '{topic}': {pts.shape[0]} joints for {len(names)} joint_names")
            stamps.append(_header_stamp(msg))
            rows.append(pts)
    if not stamps:
        raise BagError(f"{path}: topic '{topic}' has no messages")
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    return JointTrack(np.asarray(stamps, dtype=np.int64)[order], names, np.stack(rows)[order])


# =========================================================================== scenes
_IMAGE_TOPIC = re.compile(r"^/cameras/([^/]+)/image_raw(/compressed)?$")
#: Frames held back while waiting for the images of all cameras (out-of-order tolerance).
_MAX_PENDING = 16


def _camera_from_ros(name: str, info: Any, extr: Any, where: str) -> Camera:
    """Camera from CameraInfo and a TransformStamped (messages.camera_from_msgs), errors naming the bag."""
    from .messages import camera_from_msgs

    try:
        return camera_from_msgs(name, info, extr)
    except CalibrationError as exc:
        raise BagError(f"{where}: {exc}") from None


class Scene:
    """A multi-camera recording opened by :func:`read_scene`.

    cameras: list[Camera] in the bag's topic order (from camera_info + extrinsics, or as given);
    image_topics: camera name -> image topic; n_frames: image messages of the busiest camera;
    truth: :class:`JointTrack` of ``/artrack/ground_truth`` (None if absent; read on first use);
    truncated / problem: opened with ``allow_truncated`` and damaged (what is wrong).
    """

    def __init__(
        self,
        path: Path,
        cameras: list[Camera],
        image_topics: dict[str, str],
        n_frames: int,
        has_truth: bool,
        truncated: bool,
        problem: str | None = None,
    ):
        self.path = path
        self.cameras = cameras
        self.image_topics = image_topics
        self.n_frames = n_frames
        self.has_truth = has_truth
        self.truncated = truncated
        self.problem = problem  # what is wrong with a truncated bag (None when complete)

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @functools.cached_property
    def truth(self) -> JointTrack | None:
        if not self.has_truth:
            return None
        return read_body_topic(self.path, GROUND_TRUTH_TOPIC, allow_truncated=self.truncated)

    def truth_at(self, stamp_ns: int) -> np.ndarray | None:
        """Ground-truth joints (J, 3) at exactly ``stamp_ns``, or None."""
        tr = self.truth
        if tr is None:
            return None
        i = int(np.searchsorted(tr.stamps, stamp_ns))
        return tr.joints[i] if i < len(tr.stamps) and tr.stamps[i] == stamp_ns else None

    def frames(self, cameras: Sequence[str] | None = None) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
        """Yield ``(stamp_ns, {camera name: (H, W, 3) uint8 BGR})`` in increasing header-stamp order.

        Images with the same header stamp form one frame; a frame is complete when every
        camera has delivered, and frames missing a camera are still yielded (with fewer
        entries) once newer ones complete. An image older than an already yielded frame is
        dropped. Image sizes are checked against the cameras (BagError).
        """
        names = list(cameras) if cameras is not None else self.camera_names
        by_name = {c.name: c for c in self.cameras}
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise BagError(f"{self.path}: no camera named '{unknown[0]}'")
        topic_to_name = {self.image_topics[n]: n for n in names}
        pending: dict[int, dict[str, np.ndarray]] = {}
        last = None
        with open_bag(self.path, allow_truncated=self.truncated) as bag:
            for topic, stamp, img in bag.images(list(topic_to_name)):
                name = topic_to_name[topic]
                cam = by_name[name]
                if img.shape[:2] != (cam.height, cam.width):
                    raise BagError(
                        f"{self.path}: topic '{topic}': image at stamp {stamp} is "
                        f"{img.shape[1]}x{img.shape[0]}, camera_info says {cam.width}x{cam.height}"
                    )
                if last is not None and stamp <= last:
                    continue
                group = pending.setdefault(stamp, {})
                group[name] = img
                if len(group) == len(names):
                    for s in sorted(k for k in pending if k <= stamp):
                        last = s
                        yield s, pending.pop(s)
                elif len(pending) > _MAX_PENDING:
                    last = min(pending)
                    yield last, pending.pop(last)
            for s in sorted(pending):
                yield s, pending.pop(s)


def read_scene(
    path: str | os.PathLike, *, cameras: Sequence[Camera] | None = None, allow_truncated: bool = False
) -> Scene:
    """Open a multi-camera recording (layout in the module docstring).

    Cameras are rebuilt from the first camera_info and extrinsics of every camera with an
    image topic (raw preferred over ``/compressed``); pass ``cameras`` (e.g. from
    ``load_calibration``) to use an external calibration instead — then only their names
    must have image topics. Raises BagError naming the missing topic.
    """
    p = Path(path)
    with open_bag(p, allow_truncated=allow_truncated) as bag:
        topics = bag.topics()
        counts = bag.message_counts()
        image_topics: dict[str, str] = {}
        for t in topics:
            m = _IMAGE_TOPIC.match(t)
            if m and (m.group(1) not in image_topics or not m.group(2)):
                image_topics[m.group(1)] = t
        if cameras is not None:
            for c in cameras:
                if c.name not in image_topics:
                    raise BagError(
                        f"{p}: no topic '{camera_topic(c.name, 'image_raw')}' for camera '{c.name}'"
                    )
            cams = list(cameras)
            image_topics = {c.name: image_topics[c.name] for c in cams}
        else:
            if not image_topics:
                raise BagError(f"{p}: no camera image topics (/cameras/<name>/image_raw[/compressed])")
            cams = _read_cameras(bag, p, list(image_topics), topics)
        n_frames = max((counts.get(image_topics[c.name], 0) for c in cams), default=0)
        return Scene(p, cams, image_topics, n_frames, GROUND_TRUTH_TOPIC in topics, bag.truncated,
                     bag.problem)


def _read_cameras(bag: BagReader, p: Path, names: list[str], topics: dict[str, str]) -> list[Camera]:
    wanted = {}
    for n in names:
        for leaf in ("camera_info", "extrinsics"):
            t = camera_topic(n, leaf)
            if t not in topics:
                raise BagError(f"{p}: no topic '{t}' (calibration of camera '{n}')")
            wanted[t] = (n, leaf)
    got: dict[tuple[str, str], Any] = {}
    for topic, _, msg in bag.messages(list(wanted)):
        key = wanted[topic]
        if key not in got:
            got[key] = msg
            if len(got) == len(wanted):
                break
    for t, key in wanted.items():
        if key not in got:
            raise BagError(f"{p}: topic '{t}' has no readable messages")
    return [_camera_from_ros(n, got[(n, "camera_info")], got[(n, "extrinsics")], str(p)) for n in names]


def write_scene_bag(
    path: str | os.PathLike,
    cameras: Sequence[Camera],
    frames: Iterable[Any],
    *,
    joint_names: Sequence[str] | None = None,
    truth: bool = True,
    image_format: str = "raw",
    storage: str | None = None,
    extra_topics: dict[str, str] | None = None,
) -> int:
    """Write a multi-camera scene (layout in the module docstring); returns the number of frames.

    extra_topics: {topic: msgtype} of further per-frame messages (e.g. point clouds, an object
    pose); a frame's ``extra_messages`` ((topic, rosbags message) pairs) are written at its stamp.

    frames: iterable of objects with ``stamp_ns`` (int ns), ``images`` ({camera name: (H, W, 3)
    uint8 BGR}, sizes as calibrated) and, for ``truth``, ``joints`` ((J, 3) world, m) named by
    ``joint_names``. image_format: ``"raw"`` (sensor_msgs/Image bgr8 on ``.../image_raw``),
    ``"png"`` or ``"jpeg"`` (sensor_msgs/CompressedImage on ``.../image_raw/compressed``).
    Extrinsics are written once, stamped with the first frame; camera_info with every frame.
    """
    from .messages import body_msg, camera_info_msg, extrinsics_msg, header_msg, image_msg, rosbags_factory
    from .types import BodyEstimate

    if image_format not in ("raw", "png", "jpeg"):
        raise ValueError(f"image_format must be 'raw', 'png' or 'jpeg', got {image_format!r}")
    f = rosbags_factory()
    by_name = {c.name: c for c in cameras}
    it = iter(frames)
    first = next(it, None)
    n = 0
    with BagWriter(path, storage=storage) as bag:
        for c in cameras:
            if image_format == "raw":
                bag.add_topic(camera_topic(c.name, "image_raw"), "sensor_msgs/msg/Image")
            else:
                bag.add_topic(camera_topic(c.name, "image_raw/compressed"), "sensor_msgs/msg/CompressedImage")
            bag.add_topic(camera_topic(c.name, "camera_info"), "sensor_msgs/msg/CameraInfo", qos="latched")
            bag.add_topic(
                camera_topic(c.name, "extrinsics"), "geometry_msgs/msg/TransformStamped", qos="latched"
            )
        if truth:
            bag.add_topic(GROUND_TRUTH_TOPIC, "artrack_msgs/msg/TrackedBody")
        for topic, msgtype in (extra_topics or {}).items():
            bag.add_topic(topic, msgtype)
        t0 = int(first.stamp_ns) if first is not None else 0
        for c in cameras:
            bag.write(camera_topic(c.name, "extrinsics"), t0, extrinsics_msg(f, c, t0, WORLD_FRAME))
        frame = first
        while frame is not None:
            stamp = int(frame.stamp_ns)
            for name, img in frame.images.items():
                cam = by_name.get(name)
                if cam is None:
                    raise InputError(f"{path}: frame {n} has an image for unknown camera '{name}'")
                img = np.asarray(img)
                if img.shape != (cam.height, cam.width, 3) or img.dtype != np.uint8:
                    raise InputError(
                        f"{path}: frame {n} camera '{name}': image is {img.shape} {img.dtype}, "
                        f"expected ({cam.height}, {cam.width}, 3) uint8"
                    )
                bag.write(camera_topic(name, "camera_info"), stamp, camera_info_msg(f, cam, stamp))
                if image_format == "raw":
                    bag.write(camera_topic(name, "image_raw"), stamp, image_msg(f, img, stamp, cam.frame_id))
                else:
                    ok, buf = cv2.imencode(".png" if image_format == "png" else ".jpg", img)
                    if not ok:
                        raise InputError(f"{path}: frame {n} camera '{name}': {image_format} encoding failed")
                    msg = f(
                        "sensor_msgs/msg/CompressedImage",
                        header=header_msg(f, stamp, cam.frame_id),
                        format=f"bgr8; {image_format} compressed bgr8",
                        data=buf.reshape(-1),
                    )
                    bag.write(camera_topic(name, "image_raw/compressed"), stamp, msg)
            if truth and frame.joints is not None:  # no ground truth while nobody is there
                if joint_names is None:
                    raise InputError(f"{path}: joint_names are needed to write the ground truth")
                joints = np.asarray(frame.joints, dtype=np.float64).reshape(-1, 3)
                if joints.shape[0] != len(joint_names):
                    raise InputError(
                        f"{path}: frame {n}: {joints.shape[0]} ground-truth joints "
                        f"for {len(joint_names)} joint_names"
                    )
                est = BodyEstimate(
                    stamp_ns=stamp, joint_names=list(joint_names), joints=joints, links=[], blobs=[]
                )
                bag.write(GROUND_TRUTH_TOPIC, stamp, body_msg(f, est))
            for topic, msg in getattr(frame, "extra_messages", ()):
                bag.write(topic, stamp, msg)
            n += 1
            frame = next(it, None)
    return n
