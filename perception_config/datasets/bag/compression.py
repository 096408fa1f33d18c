"""Message-level compression of rosbag2 bags: each message's CDR bytes compressed on its own.

rosbag2 writes it with `ros2 bag record --compression-mode message --compression-format zstd`
(metadata.yaml: compression_mode MESSAGE); other recorders use lz4 frames. A payload is
recognised by its frame's magic number, so a bare .mcap without metadata.yaml reads too: CDR
starts with a 0x00 encapsulation byte, which neither magic number does. (MCAP chunk compression,
zstd or lz4, is undone by the mcap reader itself.)
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Iterator

from .errors import BagFormatError

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
LZ4_MAGIC = b"\x04\x22\x4d\x18"
MAX_MESSAGE_BYTES = 512 * 1024 * 1024  # a message that decompresses to more than this is damage


class MessageDecompressionError(ValueError):
    """A compressed message that does not decompress (damaged, or larger than the limit)."""


def payload_compression(data: bytes) -> str | None:
    """'zstd' or 'lz4' for a compressed message, None for plain CDR."""
    head = bytes(data[:4])
    if head == ZSTD_MAGIC:
        return "zstd"
    if head == LZ4_MAGIC:
        return "lz4"
    return None


def decompress_message(data: bytes) -> bytes:
    """The CDR bytes of a message, decompressed if it is a zstd or lz4 frame."""
    kind = payload_compression(data)
    if kind is None:
        return data
    try:
        if kind == "zstd":
            import io

            import zstandard

            with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(bytes(data)), read_across_frames=True) as r:
                out = r.read(MAX_MESSAGE_BYTES + 1)
            size = zstandard.frame_content_size(bytes(data[:18]))
            if size >= 0 and len(out) != size:
                raise ValueError(f"{len(out)} of its {size} bytes decompress: the frame is cut")
        else:
            import lz4.frame

            dec = lz4.frame.LZ4FrameDecompressor()
            out = dec.decompress(bytes(data), max_length=MAX_MESSAGE_BYTES + 1)
            if not dec.eof and len(out) <= MAX_MESSAGE_BYTES:
                raise ValueError("the frame is cut")
    except Exception as exc:
        raise MessageDecompressionError(f"damaged {kind}-compressed message ({type(exc).__name__}: {exc})") from None
    if len(out) > MAX_MESSAGE_BYTES:
        raise MessageDecompressionError(f"{kind}-compressed message decompresses to more than "
                                        f"{MAX_MESSAGE_BYTES} bytes")
    return out


def decompress_stream(items: Iterable[tuple[Any, int, bytes]],
                      path: Path) -> Iterator[tuple[Any, int, bytes, str | None]]:
    """(channel, log_time_ns, CDR bytes, how it was stored) of (channel, log_time_ns, stored bytes);
    a damaged compressed message is a BagFormatError naming the file, topic and log time."""
    for ch, log_time, data in items:
        kind = payload_compression(data)
        if kind is not None:
            try:
                data = decompress_message(data)
            except MessageDecompressionError as exc:
                raise BagFormatError(f"{path}: topic {ch.topic}, log time {log_time / 1e9:.9f} s: {exc}") from None
        yield ch, log_time, data, kind
