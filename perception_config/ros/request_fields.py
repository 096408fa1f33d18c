"""The one parser of what requests carry: object ids, stamps, method lists, and echoed text.

Every node parses these here, so they all accept and refuse the same things: before, the
configurator and scoring_node took " 1", "+1", "١" (Arabic-Indic one), "1\\n" and "000…01" as
object 1 while generation_node and pick_node refused them, and a stamp with nanosec >= 1e9
silently named the next second's frame. Messages echo at most a short prefix of bad input.
"""
from __future__ import annotations

from typing import Any, Iterable

MAX_OBJECT_ID = 64  # characters
MAX_METHOD = 64  # characters of one method name
MAX_METHODS = 16  # methods in one request
ECHO = 40  # characters of bad input quoted in a message
NANOSECONDS = 1_000_000_000


def excerpt(text: Any, limit: int = ECHO) -> str:
    """`text` quoted for a message: repr of at most `limit` characters, then how many more."""
    text = str(text)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


def parse_object_id(text: Any) -> str:
    """The canonical object id: ASCII digits without sign, space or leading zeros ("0" is "0"),
    at most MAX_OBJECT_ID characters (BOP models are obj_NNNNNN.ply, ids are integers).
    ValueError naming what is wrong."""
    if not isinstance(text, str):
        raise ValueError(f"object_id must be text, got {type(text).__name__}")
    if not text:
        raise ValueError("object_id is empty")
    if len(text) > MAX_OBJECT_ID:
        raise ValueError(f"object_id is {len(text)} characters long (at most {MAX_OBJECT_ID}): {excerpt(text)}")
    if not (text.isascii() and text.isdigit()):
        raise ValueError(f"object_id {excerpt(text)} is not an integer id (ASCII digits only, no sign or space)")
    if len(text) > 1 and text[0] == "0":
        raise ValueError(f"object_id {excerpt(text)} has leading zeros (write {text.lstrip('0') or '0'})")
    return text


def parse_stamp(stamp: Any, what: str = "stamp") -> int:
    """A builtin_interfaces/Time as nanoseconds (0 = the latest frame); ValueError for a negative
    sec or a nanosec of one second or more (which would alias another frame)."""
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if sec < 0:
        raise ValueError(f"{what}.sec is negative ({sec})")
    if not 0 <= nanosec < NANOSECONDS:
        raise ValueError(f"{what}.nanosec must be in 0..999999999, got {nanosec}")
    return sec * NANOSECONDS + nanosec


def parse_method(text: Any, what: str = "method") -> str:
    """A method name as sent (looked up by the node); ValueError when it is too long to be one."""
    if not isinstance(text, str):
        raise ValueError(f"{what} must be text, got {type(text).__name__}")
    if len(text) > MAX_METHOD:
        raise ValueError(f"{what} is {len(text)} characters long (at most {MAX_METHOD}): {excerpt(text)}")
    return text


def parse_methods(methods: Iterable[Any]) -> list[str]:
    """A list of method names: at most MAX_METHODS, each once."""
    methods = list(methods)
    if len(methods) > MAX_METHODS:
        raise ValueError(f"{len(methods)} methods requested (at most {MAX_METHODS})")
    names = [parse_method(m) for m in methods]
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise ValueError(f"method {excerpt(name)} is requested twice")
        seen.add(name)
    return names
