"""rosbag2 sqlite3 storage (.db3 files: the default before ROS 2 Iron), read through `rosbags`.

`Db3File` offers what the bag readers use of `McapFile` (channels, counts, time range, messages in
log-time order), so `read_bag`, `bag_info`, `iter_messages` and the replay read .db3 bags like
MCAP ones. Message definitions come from the file's message_definitions table (rosbag2 >= Iron
and rosbags write it); older files have none and the decoder falls back to the definitions we know.
"""
from __future__ import annotations

import weakref
from pathlib import Path
from typing import Iterator

from .compression import decompress_stream
from .errors import BagFormatError, reading
from .mcap_reader import _ChannelInfo, _Schema


class Db3File:
    """One rosbag2 sqlite3 file; opening it checks that it is a rosbag2 database."""

    header_profile = ""  # MCAP header fields; a .db3 file has none
    header_library = ""

    def __init__(self, path: Path):
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        self.path = path
        self.size = path.stat().st_size
        self.damage: str | None = None
        self.damage_offset: int | None = None
        self.corrupt = False
        self.chunk_compression: set[str] = set()
        self.metadata: dict[str, dict[str, str]] = {}
        self._reader = Sqlite3Reader(path)
        try:
            self._reader.open()
        except Exception as exc:  # rosbags' ReaderError, apsw errors
            raise BagFormatError(f"{path}: not a readable rosbag2 sqlite3 database ({exc})") from None
        weakref.finalize(self, self._reader.close)  # the database connection closes with this object
        self._conns = {c.id: c for c in self._reader.connections}
        fmt = {1: "ros2msg", 2: "ros2idl"}  # rosbags MessageDefinitionFormat.MSG / IDL
        self._channels = {
            c.id: _ChannelInfo(c.id, c.topic, c.ext.serialization_format,
                               _Schema(c.msgtype, fmt.get(c.msgdef.format.value, ""), c.msgdef.data.encode()))
            for c in self._conns.values()}
        self.counts = {c.id: int(c.msgcount) for c in self._conns.values()}
        md = self._reader.metadata
        self.times = [md.start_time, md.end_time - 1] if md.message_count else []

    @property
    def complete(self) -> bool:
        return True

    def verify(self) -> bool:
        """sqlite3 has no per-record checksums; a damaged database fails when opened or read."""
        return True

    def channels(self) -> dict[int, _ChannelInfo]:
        return self._channels

    def messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes]]:
        """(channel, log_time_ns, CDR bytes) in log-time order; message-compressed ones decompressed."""
        for ch, log_time, data, _kind in self.stored_messages(channel_ids):
            yield ch, log_time, data

    def stored_messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes, str | None]]:
        """As `messages`, with how each message was stored ('zstd', 'lz4' or None: plain CDR)."""
        return decompress_stream(self._rows(channel_ids), self.path)

    def _rows(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes]]:
        conns = [c for i, c in self._conns.items() if channel_ids is None or i in channel_ids]
        if not conns:
            return
        for conn, log_time, data in reading(self._reader.messages(conns), f"{self.path}: damaged sqlite3 data"):
            yield self._channels[conn.id], log_time, data

    def truncation_message(self) -> str:
        return f"{self.path} is damaged ({self.damage})"
