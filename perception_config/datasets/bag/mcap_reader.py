"""Reading MCAP files: bag file discovery, damaged files, channels, raw and decoded messages.

A bag is a .mcap or .db3 file or a rosbag2 directory (metadata.yaml lists its files; without it,
every .mcap, else every .db3 file in it). A file without a valid end (no footer: the recorder was
killed, the copy was cut) is read in file order up to the damage (`McapFile.damage`,
`damage_offset`). Chunk compression (zstd, lz4) is undone by the mcap reader, message-level
compression by `compression.decompress_message`. Type names are given as 'pkg/msg/Name' whether
the bag wrote 'pkg/msg/Name' or 'pkg/Name'. `make_decoder` decodes a channel's messages from the
bag's own schema, or a known definition (ours, else the rosbags typestore) for a bag without one.
(.db3 files: sqlite_reader.py; `iter_messages` and opening either kind: storage.py.)
"""
from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import yaml

from .compression import decompress_stream
from .definitions import definition
from .errors import BagFormatError, BagTruncatedError, reading
from .type_names import normalize_type_name

_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
MAX_RECORD_BYTES = 512 * 1024 * 1024  # an MCAP record, or a chunk's declared uncompressed size, above this is damage


class BagMessage(NamedTuple):
    """A raw serialized message, for a replay node that publishes without decoding."""

    topic: str
    type: str  # schema name, e.g. sensor_msgs/msg/Image
    log_time_ns: int
    data: bytes  # CDR, as a ROS 2 publisher would send it


def bag_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The rosbag2_bagfile_information of a bag directory's metadata.yaml ({} for a file or without one)."""
    meta = Path(path) / "metadata.yaml"
    if not meta.is_file():
        return {}
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise ValueError("rosbag2_bagfile_information is not a mapping")
        return info
    except Exception as exc:
        raise BagFormatError(f"{meta}: not a readable rosbag2 metadata.yaml ({exc})") from None


def bag_files(path: str | os.PathLike) -> list[Path]:
    """The .mcap / .db3 files of a bag: the file itself, or those of a directory (as its
    metadata.yaml lists them, else every .mcap file in it, else every .db3 file)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such bag: {p}")
    if p.is_file():
        return [p]
    meta = p / "metadata.yaml"
    files: list[Path] = []
    if meta.is_file():
        info = bag_metadata(p)
        storage = info.get("storage_identifier", "mcap")
        if storage not in ("mcap", "sqlite3"):
            raise BagFormatError(f"{meta}: rosbag2 storage {storage!r} is not supported, only mcap and sqlite3 "
                                 "(convert with `ros2 bag convert`)")
        if str(info.get("compression_mode", "")).lower() == "file":
            raise BagFormatError(f"{meta}: the bag's files are compressed whole (compression_mode FILE, "
                                 f"{info.get('compression_format')}): decompress them first (e.g. `zstd -d`) "
                                 "and remove the compression entries from metadata.yaml")
        try:
            files = [p / Path(f).name for f in info.get("relative_file_paths", [])]
        except Exception as exc:
            raise BagFormatError(f"{meta}: not a readable rosbag2 metadata.yaml ({exc})") from None
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise BagFormatError(f"{p}: metadata.yaml lists files that are missing: {missing}")
    if not files:
        files = sorted(p.glob("*.mcap")) or sorted(p.glob("*.db3"))
    if not files:
        raise BagFormatError(f"{p}: no .mcap or .db3 file in this directory")
    return files


class _Schema(NamedTuple):
    name: str
    encoding: str
    data: bytes


class _ChannelInfo(NamedTuple):
    id: int
    topic: str
    message_encoding: str
    schema: _Schema | None


class McapFile:
    """One MCAP file: indexed and complete, or damaged (read in file order up to the damage)."""

    def __init__(self, path: Path):
        from mcap.reader import SeekingReader

        self.path = path
        self.size = path.stat().st_size
        self.damage: str | None = None  # why the file is not complete
        self.damage_offset: int | None = None  # bytes read fine before the damage
        self.corrupt = False  # a complete file (with footer) whose records are damaged (verify)
        self._channels: dict[int, _ChannelInfo] | None = None
        self.counts: dict[int, int] = {}
        self.times: list[int] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.chunk_compression: set[str] = set()  # '' = chunks stored uncompressed
        with open(path, "rb") as f:
            head = f.read(len(_SQLITE_MAGIC))
            if head.startswith(_SQLITE_MAGIC):
                raise BagFormatError(f"{path}: a rosbag2 sqlite3 (.db3) file, not MCAP (open it with "
                                     "storage.open_bag_file)")
            if not head.startswith(_MAGIC):
                if len(head) < len(_MAGIC) and _MAGIC.startswith(head):
                    raise BagTruncatedError(f"{path}: truncated before its first MCAP record ({self.size} bytes)")
                raise BagFormatError(f"{path}: not an MCAP file (bad magic bytes)")
            f.seek(max(0, self.size - len(_MAGIC)))
            tail = f.read()
            self.summary = None
            self.header_profile = ""
            self.header_library = ""
            if self.size < 2 * len(_MAGIC) + 29 or tail != _MAGIC:
                self.damage = "no MCAP footer: the recording was cut or the recorder was killed"
            else:
                try:
                    f.seek(0)
                    reader = SeekingReader(f, record_size_limit=MAX_RECORD_BYTES)
                    self.summary = reader.get_summary()
                    big = [c.uncompressed_size for c in (self.summary.chunk_indexes if self.summary else [])
                           if c.uncompressed_size > MAX_RECORD_BYTES]
                    if big:
                        raise ValueError(f"a chunk declares {big[0]} uncompressed bytes, more than the "
                                         f"{MAX_RECORD_BYTES}-byte limit")
                    self.chunk_compression = {c.compression for c in self.summary.chunk_indexes} \
                        if self.summary else set()
                    h = reader.get_header()
                    self.header_profile, self.header_library = h.profile, h.library
                except Exception as exc:  # damaged footer/summary
                    self.summary = None
                    self.damage = f"unreadable MCAP summary/footer ({exc})"

    @property
    def complete(self) -> bool:
        return self.damage is None

    def verify(self) -> bool:
        """Read every record of a complete file, checking each chunk's CRC and decompression;
        True if all are intact. A damaged file is then read like a cut one: in file order, up to
        the damage (`corrupt` is set, the summary's index and counts are no longer trusted).
        Call before `channels()`."""
        if self.damage is not None:
            return False
        for _ in self._record_batches():
            pass
        if self.damage is None:
            self.damage = self._section_crc_damage()
        if self.damage is not None:
            self.corrupt = True
            self.summary = None
            self._channels = None
        return not self.corrupt

    def _section_crc_damage(self) -> str | None:
        """The footer's summary CRC and the DataEnd record's data-section CRC, where recorded (0 =
        not recorded, MCAP spec); mcap's readers check neither. None if they match."""
        footer_len = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary_start, summary_offset_start, summary_crc
        footer_at = self.size - len(_MAGIC) - footer_len
        with open(self.path, "rb") as f:
            f.seek(footer_at)
            op, _n, summary_start, _sos, summary_crc = struct.unpack("<BQQQI", f.read(footer_len))
            if op != 0x02 or summary_start > footer_at:
                return "damaged MCAP footer"
            if summary_crc and summary_start and _crc32(f, summary_start, footer_at + footer_len - 4) != summary_crc:
                return "damaged MCAP summary section (summary CRC mismatch)"
            data_end_at = (summary_start or footer_at) - 13  # DataEnd: opcode, length, data_section_crc
            if data_end_at >= len(_MAGIC):
                f.seek(data_end_at)
                op, _n, data_crc = struct.unpack("<BQI", f.read(13))
                if op == 0x0F and data_crc and _crc32(f, 0, data_end_at) != data_crc:
                    return "damaged MCAP data section (data section CRC mismatch)"
        return None

    # -- sequential scan: damaged files and files without an index ------------------------------
    def _record_batches(self) -> Iterator[list]:
        """The file's records in file order, a chunk's records as one batch (its CRC checked).

        Stops at the first record that cannot be read and notes the damage and its offset.
        """
        from mcap.records import Chunk, Footer, Header
        from mcap.stream_reader import StreamReader, breakup_chunk

        with open(self.path, "rb") as f:
            records = StreamReader(f, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records
            good = len(_MAGIC)
            while True:
                try:
                    rec = next(records)
                    if isinstance(rec, Chunk) and rec.uncompressed_size > MAX_RECORD_BYTES:  # not decompressed
                        raise ValueError(f"a chunk declares {rec.uncompressed_size} uncompressed bytes, more than "
                                         f"the {MAX_RECORD_BYTES}-byte limit")
                    batch = breakup_chunk(rec, validate_crc=True) if isinstance(rec, Chunk) else [rec]
                    good = f.tell()
                except StopIteration:
                    return
                except Exception as exc:  # cut or corrupt: everything before `good` was intact
                    if self.damage is None:
                        self.damage = f"damaged MCAP data ({type(exc).__name__}: {exc})"
                    self.damage_offset = good
                    return
                if isinstance(rec, Chunk):
                    self.chunk_compression.add(rec.compression)
                if isinstance(rec, Header):
                    self.header_profile, self.header_library = rec.profile, rec.library
                yield batch
                if isinstance(rec, Footer):
                    return

    def channels(self) -> dict[int, _ChannelInfo]:
        """Channels by id; also fills message counts, time range and metadata records."""
        if self._channels is not None:
            return self._channels
        chans: dict[int, _ChannelInfo] = {}
        counts: dict[int, int] = {}
        times: list[int] = []
        metadata: dict[str, dict[str, str]] = {}
        if self.summary is not None and self.summary.statistics is not None:
            schemas = {i: _Schema(s.name, s.encoding, s.data) for i, s in self.summary.schemas.items()}
            for i, c in self.summary.channels.items():
                chans[i] = _ChannelInfo(i, c.topic, c.message_encoding, schemas.get(c.schema_id))
            st = self.summary.statistics
            counts = dict(st.channel_message_counts)
            if st.message_count:
                times = [st.message_start_time, st.message_end_time]
            metadata = self._read_metadata_indexed()
        else:
            from mcap.records import Channel, Message, Metadata, Schema

            scm: dict[int, _Schema] = {}
            for batch in self._record_batches():
                for r in batch:
                    if isinstance(r, Schema):
                        scm[r.id] = _Schema(r.name, r.encoding, r.data)
                    elif isinstance(r, Channel):
                        chans[r.id] = _ChannelInfo(r.id, r.topic, r.message_encoding, scm.get(r.schema_id))
                    elif isinstance(r, Message):
                        counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
                        times = [min(times[0], r.log_time), max(times[1], r.log_time)] if times else [r.log_time] * 2
                    elif isinstance(r, Metadata):
                        metadata[r.name] = dict(r.metadata)
        self._channels, self.counts, self.times, self.metadata = chans, counts, times, metadata
        return chans

    def _read_metadata_indexed(self) -> dict[str, dict[str, str]]:
        from mcap.reader import SeekingReader

        out: dict[str, dict[str, str]] = {}
        try:
            with open(self.path, "rb") as f:
                for m in SeekingReader(f, record_size_limit=MAX_RECORD_BYTES).iter_metadata():
                    out[m.name] = dict(m.metadata)
        except Exception:
            pass
        return out

    def messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes]]:
        """(channel, log_time_ns, CDR bytes): log-time order when indexed, else file order;
        message-compressed payloads decompressed (BagFormatError naming file, topic and time if damaged)."""
        for ch, log_time, data, _kind in self.stored_messages(channel_ids):
            yield ch, log_time, data

    def stored_messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes, str | None]]:
        """As `messages`, with how each message was stored ('zstd', 'lz4' or None: plain CDR)."""
        return decompress_stream(self._raw_messages(channel_ids), self.path)

    def _raw_messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes]]:
        chans = self.channels()
        if self.summary is not None and self.summary.chunk_indexes:
            from mcap.reader import SeekingReader

            topics = None if channel_ids is None else sorted({chans[i].topic for i in channel_ids})
            if topics == []:
                return
            with open(self.path, "rb") as f:
                reader = SeekingReader(f, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES)
                for _schema, channel, message in reading(reader.iter_messages(topics=topics, log_time_order=True),
                                                         f"{self.path}: damaged MCAP data"):
                    yield chans[channel.id], message.log_time, message.data
            return
        from mcap.records import Message

        for batch in self._record_batches():
            for r in batch:
                if isinstance(r, Message) and (channel_ids is None or r.channel_id in channel_ids):
                    ch = chans.get(r.channel_id)
                    if ch is not None:
                        yield ch, r.log_time, r.data

    def truncation_message(self) -> str:
        intact = f"; its first {self.damage_offset} of {self.size} bytes are intact" if self.damage_offset else ""
        return f"{self.path} is truncated or damaged ({self.damage}){intact}"


def _crc32(f: Any, start: int, end: int, block: int = 8 * 1024 * 1024) -> int:
    """CRC32 of bytes [start, end) of an open file, read in blocks (a bag may be gigabytes)."""
    f.seek(start)
    crc, left = 0, end - start
    while left > 0:
        data = f.read(min(block, left))
        if not data:
            break
        crc = zlib.crc32(data, crc)
        left -= len(data)
    return crc


def schema_name(ch: _ChannelInfo) -> str:
    """The channel's type as 'pkg/msg/Name' (also for a bag that wrote 'pkg/Name'); '' without a schema."""
    return normalize_type_name(ch.schema.name) if ch.schema is not None else ""


def known_definition(type_name: str) -> str | None:
    """The ros2msg definition text (with its nested types) of a type the bag gives no definition
    for (rosbag2 sqlite3 bags before Iron): the rosbags typestore's (ROS 2 Kilted + ours)."""
    try:
        return definition(type_name)
    except BagFormatError:
        return None


def make_decoder(ch: _ChannelInfo, path: Path) -> Callable[[bytes], Any]:
    """CDR decoder of a channel, from the bag's own schema, or ours for a type we ship."""
    from mcap_ros2._dynamic import generate_dynamic

    if ch.message_encoding != "cdr":
        raise BagFormatError(f"{path}: topic {ch.topic} has message encoding {ch.message_encoding!r}, not cdr")
    name = schema_name(ch)
    text = None
    if ch.schema is not None and ch.schema.encoding == "ros2msg" and ch.schema.data:
        text = ch.schema.data.decode("utf-8", errors="replace")
    else:  # e.g. a ros2idl or empty definition of a standard type
        text = known_definition(name)
    if text is None:
        enc = ch.schema.encoding if ch.schema is not None else "none"
        raise BagFormatError(f"{path}: topic {ch.topic} ({name or 'no schema'}) has a {enc!r} schema this reader "
                             "cannot decode (ros2msg needed)")
    try:
        return generate_dynamic(name, text)[name]
    except Exception as exc:
        raise BagFormatError(f"{path}: topic {ch.topic}: "
                             f"cannot parse the message definition of {name} ({exc})") from None
