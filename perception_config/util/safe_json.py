"""JSON from files that may be hostile: size and nesting depth checked before parsing.

Python's json parser recurses once per nesting level: a file of 100,000 '[' raises
RecursionError (or, with a raised recursion limit, crashes the interpreter), and a file of
any size is read whole. `read_json_file` / `loads_limited` check, in this order: the file is
a regular file (not a directory, FIFO or device), its size is at most `max_bytes`, the text is
UTF-8, the bracket depth (outside strings) is at most `max_depth`; only then is it parsed.
Every failure is a `JsonLimitError` (a ValueError) naming the file and the problem; callers
re-raise it as their own error type (PolicyError, BopFormatError).
"""
from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path
from typing import Any

import numpy as np

MAX_JSON_BYTES = 256 * 1024 * 1024  # default size limit of a JSON document (256 MiB)
MAX_JSON_DEPTH = 64  # default limit of nested arrays/objects (the project's files use <= 8)

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


class JsonLimitError(ValueError):
    """A JSON document that is not a regular file, too large, too deep, or not valid JSON."""


def regular_file_size(path: str | os.PathLike, what: str = "file") -> int:
    """The size (bytes) of a regular file; FileNotFoundError, or JsonLimitError for a directory
    or a special file (FIFO, socket, device: reading those could block or never end)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} not found: {path}") from None
    if stat.S_ISDIR(st.st_mode):
        raise JsonLimitError(f"{path}: is a directory, not a {what}")
    if not stat.S_ISREG(st.st_mode):
        raise JsonLimitError(f"{path}: is not a regular file (a FIFO, socket or device), not a {what}")
    return st.st_size


def read_limited(path: str | os.PathLike, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of a regular file of at most `max_bytes` (checked before reading, and while)."""
    size = regular_file_size(path, what)
    if size > max_bytes:
        raise JsonLimitError(f"{path}: {size} bytes, more than the {max_bytes}-byte limit of a {what}")
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:  # grew while being read
        raise JsonLimitError(f"{path}: more than the {max_bytes}-byte limit of a {what}")
    return data


def json_depth(data: bytes) -> int:
    """The deepest nesting of arrays/objects in JSON text (brackets inside strings ignored).
    Linear time, no recursion: strings are blanked by a regular expression, then the brackets
    are counted with a cumulative sum."""
    stripped = _STRING.sub(b'""', data)
    a = np.frombuffer(stripped, np.uint8)
    steps = (np.isin(a, (ord("["), ord("{"))).astype(np.int64)
             - np.isin(a, (ord("]"), ord("}"))).astype(np.int64))
    return int(np.cumsum(steps).max()) if steps.size else 0


def loads_limited(data: bytes, source: str, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse JSON bytes after the size and depth checks; JsonLimitError naming `source`."""
    if len(data) > max_bytes:
        raise JsonLimitError(f"{source}: {len(data)} bytes of JSON, more than the {max_bytes}-byte limit")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise JsonLimitError(f"{source}: corrupt JSON (not UTF-8 text: {e.reason})") from None
    depth = json_depth(data)
    if depth > max_depth:
        raise JsonLimitError(f"{source}: JSON nested {depth} levels deep, more than the limit of {max_depth}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise JsonLimitError(f"{source}: corrupt JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except (RecursionError, ValueError) as e:  # the depth scan is the guard; this is its backstop
        raise JsonLimitError(f"{source}: JSON that cannot be parsed ({type(e).__name__}: {e})") from None


def read_json_file(path: str | os.PathLike, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH,
                   what: str = "JSON file") -> Any:
    """The JSON content of a regular file within the size and depth limits (module docstring)."""
    return loads_limited(read_limited(path, max_bytes, what), str(Path(path)), max_bytes, max_depth)
