"""The errors and warnings of reading and writing bags."""
from __future__ import annotations

import signal
from pathlib import Path
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


class BagFormatError(ValueError):
    """A bag that cannot be read as RGB-D frames; the message names the file, topic and problem."""


def reading(records: Iterable[T], what: str) -> Iterator[T]:
    """The records of a storage library's reader; whatever it raises on damaged data becomes a
    BagFormatError "<what> (<error>)" (the caller names the file and the storage)."""
    it = iter(records)
    while True:
        try:
            record = next(it)
        except StopIteration:
            return
        except Exception as exc:
            raise BagFormatError(f"{what} ({type(exc).__name__}: {exc})") from None
        yield record


class BagTruncatedError(BagFormatError):
    """The MCAP file has no valid end (footer): a recording that was cut or killed."""


class BagWarning(UserWarning):
    pass


class BagTruncatedWarning(BagWarning):
    """Frames were read from a truncated file up to the damage; the rest is lost."""


class ImageFormatError(ValueError):
    """An image message whose encoding, step or size does not add up."""


class BagWriteInterrupted(KeyboardInterrupt):
    """Raised by the writers after Ctrl-C / SIGTERM, once the bag has been finished cleanly."""

    def __init__(self, path: Path, frames: int, signum: int):
        super().__init__(f"recording interrupted by {signal.Signals(signum).name} after {frames} frames; "
                         f"{path} is complete and readable")
        self.path = path
        self.frames = frames
        self.signum = signum
