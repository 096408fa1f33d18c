"""`bag_info`: a summary of a bag (files, storage, compression, time range, topics and counts, the
frame topics it would read or why it cannot choose them, damage)."""
from __future__ import annotations

import os
import time
from typing import Any

from .errors import BagFormatError
from .mcap_reader import bag_metadata, schema_name
from .sqlite_reader import Db3File
from .storage import first_messages, open_bag
from .topics import driver_layouts, resolve_topics


def bag_info(path: str | os.PathLike) -> dict:
    """Summary of a bag: path, files, storage (mcap | sqlite3), size, start/end (s), duration_s,
    message_count, frames (colour images that have depth and camera_info messages: an upper bound
    of what read_bag yields), topics [{topic, type, count, compression}], compression {chunk:
    MCAP chunk compressions, message: message-level compressions (seen in each topic's first
    message, and metadata.yaml's)}, frame_topics (colour, depth, camera_info, ground truth, and the
    driver layout recognised) or, when they cannot be chosen, frame_topics_error (why, with the
    candidates) and camera_layouts (every complete driver layout), recording metadata, truncated
    (the file is cut or damaged), corrupt (a complete file with a damaged chunk: CRC or
    decompression error; every chunk is read and checked, as the replay does) and damage (what and
    where). Counts of a damaged file are those of the intact records before the damage."""
    files = open_bag(path)
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    t0, t1 = None, None
    truncated: list[str] = []
    corrupt = False
    recording: dict[str, str] = {}
    profile = library = ""
    size = 0
    chunk_compression: set[str] = set()
    for f in files:
        if not f.verify():
            corrupt = corrupt or f.corrupt
        chans = f.channels()
        size += f.size
        profile, library = f.header_profile or profile, f.header_library or library
        chunk_compression |= f.chunk_compression
        for cid, n in f.counts.items():
            if cid in chans:
                counts[chans[cid].topic] = counts.get(chans[cid].topic, 0) + n
        for ch in chans.values():
            types.setdefault(ch.topic, schema_name(ch))
            counts.setdefault(ch.topic, 0)
        if f.times:
            t0 = f.times[0] if t0 is None else min(t0, f.times[0])
            t1 = f.times[1] if t1 is None else max(t1, f.times[1])
        recording.update(f.metadata.get("perception_config", {}))
        if not f.complete:
            truncated.append(f.truncation_message())
    firsts = first_messages(path) if not corrupt else {}
    msg_compression = {t: m.compression for t, m in firsts.items()}
    meta = bag_metadata(path) if os.path.isdir(path) else {}
    mode = str(meta.get("compression_mode") or "").lower()
    message_formats = sorted({c for c in msg_compression.values() if c}
                             | ({str(meta.get("compression_format"))} if mode == "message" else set()))
    info: dict[str, Any] = {
        "path": str(path),
        "files": [str(f.path) for f in files],
        "storage": "sqlite3" if all(isinstance(f, Db3File) for f in files) else "mcap",
        "size_bytes": size,
        "profile": profile,
        "library": library,
        "start": t0 / 1e9 if t0 is not None else None,
        "end": t1 / 1e9 if t1 is not None else None,
        "start_utc": (time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t0 // 1_000_000_000))
                      + f".{t0 % 1_000_000_000:09d}Z") if t0 is not None else None,
        "duration_s": (t1 - t0) / 1e9 if t0 is not None else 0.0,
        "message_count": sum(counts.values()),
        "frames": 0,
        "topics": [{"topic": t, "type": types[t], "count": counts[t], "compression": msg_compression.get(t) or "none"}
                   for t in sorted(types)],
        "compression": {"chunk": sorted(c or "none" for c in chunk_compression) or ["none"],
                        "message": message_formats or ["none"]},
        "truncated": bool(truncated),
        "corrupt": corrupt,
    }
    try:
        ft = resolve_topics(types, path)
        info["frames"] = min(counts.get(t, 0) for t in (ft.color, ft.depth, ft.camera_info) if t is not None)
        info["frame_topics"] = {k: v for k, v in ft.__dict__.items() if v}
    except BagFormatError as exc:
        info["frame_topics_error"] = str(exc)
        layouts = driver_layouts(types)
        if layouts:
            info["camera_layouts"] = [{"driver": d, "color": c, "depth": dp, "camera_info": i}
                                      for d, c, dp, i in layouts]
    if recording:
        info["recording"] = recording
    if truncated:
        info["damage"] = "; ".join(truncated)
    return info
