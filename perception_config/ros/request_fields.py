"""The one parser of what requests carry: object ids, stamps, method lists, and echoed text.

Every node parses these here, so they all accept and refuse the same things: before, the
configurator and scoring_node took " 1", "+1", "١" (Arabic-Indic one), "1\\n" and "000…01" as
object 1 while generation_node and pick_node refused them, and a stamp with nanosec >= 1e9
silently named the next second's frame. Messages echo at most a short prefix of bad input.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

from ..core.geometry import check_noise_lambda

MAX_OBJECT_ID = 64  # characters
MAX_METHOD = 64  # characters of one method name
MAX_METHODS = 16  # methods in one request
ECHO = 40  # characters of bad input quoted in a message
NANOSECONDS = 1_000_000_000
MAX_ESTIMATE_ID = 2**63 - 1  # the episode store's ids are SQLite INTEGERs
MAX_DISTANCE = 1000.0  # m: a hypothesis' position beyond this from the camera is not a pose of a part


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


def parse_estimate_id(value: Any) -> int:
    """An episode store id as EstimatePose answered it: 1..2^63-1 (0 means "not stored")."""
    eid = int(value)
    if eid == 0:
        raise ValueError("estimate_id is 0: that estimate was not stored (no episode store), so it has no outcome "
                         "to record")
    if not 1 <= eid <= MAX_ESTIMATE_ID:
        raise ValueError(f"estimate_id {eid} is out of range: estimate ids are 1..{MAX_ESTIMATE_ID}")
    return eid


def parse_noise_lambda(value: Any, what: str = "noise_lambda") -> float | None:
    """A request's noise level: None for a negative one (the node's default); ValueError for NaN or
    an infinite one (the range is checked where the level is used: core.geometry.check_noise_lambda)."""
    lam = float(value)
    if not math.isfinite(lam):
        raise ValueError(f"{what} must be a finite number (negative = the default), got {lam}")
    return None if lam < 0 else lam


def parse_position(x: float, y: float, z: float, what: str = "pose.position") -> None:
    """ValueError when a finite position lies farther than MAX_DISTANCE from the camera."""
    distance = math.hypot(float(x), float(y), float(z))
    if distance > MAX_DISTANCE:
        raise ValueError(f"{what} is {distance:.3g} m from the camera (at most {MAX_DISTANCE:g} m)")


def parse_scores(scores: Any, names: Any, what: str = "hypothesis") -> None:
    """ValueError when a hypothesis' parallel arrays scores / score_names differ in length."""
    if len(scores) != len(names):
        raise ValueError(f"{what} has {len(scores)} scores for {len(names)} score_names (parallel arrays)")


def parse_estimate_fields(request: Any) -> int:
    """Check every field of an estimate request or goal (EstimatePose.srv / .action); the
    frame's stamp in ns. max_operations and seed are uint32 (any value is meaningful),
    noise_lambda finite (negative: the configurator's) and within the lambda range."""
    stamp_ns = parse_stamp(request.frame.stamp, "frame.stamp")
    parse_object_id(request.object_id)
    lam = parse_noise_lambda(request.noise_lambda)
    if lam is not None:
        check_noise_lambda(lam, "noise_lambda (negative = the configurator's)")
    return stamp_ns
