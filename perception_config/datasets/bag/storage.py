"""The files of a bag, whatever their storage: `open_bag_file` (MCAP or rosbag2 sqlite3, told by
the file's first bytes), `iter_messages` (raw CDR of every file in order) and `first_messages`
(one message per topic, to check a bag before replaying it)."""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

from .errors import BagTruncatedWarning
from .mcap_reader import _SQLITE_MAGIC, BagMessage, McapFile, bag_files, make_decoder, schema_name
from .sqlite_reader import Db3File

BagFile = McapFile | Db3File


def open_bag_file(path: Path) -> BagFile:
    """A .db3 (sqlite3) or MCAP file of a bag; BagFormatError naming the file if it is neither."""
    with open(path, "rb") as f:
        head = f.read(len(_SQLITE_MAGIC))
    return Db3File(path) if head == _SQLITE_MAGIC else McapFile(path)


def open_bag(path: str | os.PathLike) -> list[BagFile]:
    """Every file of a bag (a file or a rosbag2 directory), opened."""
    return [open_bag_file(p) for p in bag_files(path)]


def iter_messages(path: str | os.PathLike, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Raw serialized messages (topic, type, log_time_ns, cdr bytes) of a bag file or directory.

    In log-time order per file (a damaged MCAP file: file order, up to the damage, then a
    BagTruncatedWarning). Message-level compression is undone, so a replay node can publish
    `data` as is (rclpy publish of serialized bytes). `type` is 'pkg/msg/Name' in either form's bag.
    """
    wanted = None if topics is None else set(topics)
    for f in open_bag(path):
        chans = f.channels()
        ids = None if wanted is None else {i for i, c in chans.items() if c.topic in wanted}
        for ch, log_time, data in f.messages(ids):
            yield BagMessage(ch.topic, schema_name(ch), log_time, bytes(data))
        if not f.complete:
            warnings.warn(f.truncation_message(), BagTruncatedWarning, stacklevel=2)


class FirstMessage(NamedTuple):
    message: BagMessage  # decompressed
    compression: str | None  # how it was stored: 'zstd', 'lz4' (message-level) or None
    decoded: Any  # decoded with the bag's own definition of the type (None if it does not decode)
    decode_error: str | None  # why it does not decode with the bag's definition


def first_messages(path: str | os.PathLike, topics: Iterable[str] | None = None) -> dict[str, FirstMessage]:
    """The first message of each topic that has one (decompressed, how it was stored, and decoded
    with the bag's own definition of its type), reading no further than needed."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BagTruncatedWarning)
        out: dict[str, FirstMessage] = {}
        for f in open_bag(path):
            chans = f.channels()
            todo = {i for i, c in chans.items()
                    if (topics is None or c.topic in set(topics)) and c.topic not in out and f.counts.get(i, 1)}
            if not todo:
                continue
            for ch, log_time, data, kind in f.stored_messages(todo):
                msg = BagMessage(ch.topic, schema_name(ch), log_time, bytes(data))
                decoded, error = None, None
                try:
                    decoded = make_decoder(ch, f.path)(msg.data)
                except Exception as exc:
                    error = f"{type(exc).__name__}: {exc}"[:300]
                out.setdefault(ch.topic, FirstMessage(msg, kind, decoded, error))
                todo.discard(ch.id)
                if not todo:
                    break
        return out
