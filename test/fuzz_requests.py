"""Table-driven fuzzing of every service's request: each field at its boundaries.

`cases(...)` returns, per service, the requests to send: a valid base request with one field
set to one boundary value (0, the type's max, empty, huge, negative, NaN, infinities, a
non-unit or zero quaternion, mismatched parallel arrays). Values the message type itself cannot
hold (max + 1, a negative unsigned integer) never reach a node: rclpy refuses them or wraps
them into the type's range when it serialises the request; `unsendable` lists which, checked.
The table names every field of every request; a field added to a .srv without a row here
fails `missing_fields`.
"""
from __future__ import annotations

import math
from typing import Any, Callable

U32 = 2**32 - 1
U64 = 2**64 - 1
I32 = 2**31 - 1
HUGE = 1_000_000  # characters of a huge string
MANY = 100_000  # elements of a huge array

FLOATS = (0.0, -0.0, -1.0, 1.0, 5e-324, 1e308, -1e308, math.nan, math.inf, -math.inf)
U32S = (0, 1, U32)
U64S = (0, 1, 2**63 - 1, 2**63, U64)
BOOLS = (False, True)
STRINGS = ("", "0", "1", "\u00e9", "\x00", "x" * HUGE)
STRING_LISTS = ([], [""], ["psi_c"] * 17, ["x" * 1000] * 16)
FLOAT_LISTS = ([], [math.nan], [math.inf, -math.inf, 1e308], [1.0] * MANY)

# the fields of a std_msgs/Header and a Hypothesis (prefix + field -> values)
HEADER = {"stamp.sec": (-2**31, -1, 0, I32), "stamp.nanosec": (0, 999_999_999, 1_000_000_000, U32),
          "frame_id": STRINGS}
POSE = {**{f"pose.position.{a}": FLOATS for a in "xyz"}, **{f"pose.orientation.{a}": FLOATS for a in "xyzw"}}
HYPOTHESIS = {**{f"header.{k}": v for k, v in HEADER.items()}, "object_id": STRINGS, **POSE,
              "scores": FLOAT_LISTS, "score_names": STRING_LISTS}
# values a field's type cannot hold: rclpy refuses them when the request is built
UNSENDABLE = {"uint32": (-1, U32 + 1), "uint64": (-1, U64 + 1), "int32": (-2**31 - 1, I32 + 1)}


def _set(msg: Any, path: str, value: Any) -> None:
    *parents, last = path.split(".")
    for name in parents:
        msg = getattr(msg, name)
    setattr(msg, last, list(value) if isinstance(value, list) else value)


def _fields(msg_type: Any, prefix: str = "") -> dict[str, str]:
    """Every leaf field of a message type, by dotted path -> ROS type name."""
    out: dict[str, str] = {}
    for name, kind in msg_type.get_fields_and_field_types().items():
        nested = getattr(msg_type(), name)
        if hasattr(type(nested), "get_fields_and_field_types") and not isinstance(nested, (list, tuple)):
            out.update(_fields(type(nested), f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = kind
    return out


def table(srv_type: Any) -> dict[str, tuple]:
    """Field path -> boundary values, for every field of `srv_type`'s request."""
    from perception_config_interfaces.srv import (
        EstimatePose,
        GenerateHypothesis,
        Pick,
        RefineHypothesis,
        ReportPickOutcome,
        ScoreHypothesis,
    )

    hyp = {f"hypothesis.{k}": v for k, v in HYPOTHESIS.items()}
    frame = {f"frame.{k}": v for k, v in HEADER.items()}
    return {
        GenerateHypothesis: {**frame, "object_id": STRINGS, "method": STRINGS, "noise_lambda": FLOATS,
                             "seed": U32S, "score": BOOLS},
        RefineHypothesis: {**hyp, "method": STRINGS, "seed": U32S, "score": BOOLS},
        ScoreHypothesis: {**hyp, "methods": STRING_LISTS},
        Pick: hyp,
        EstimatePose: {**frame, "object_id": STRINGS, "max_operations": U32S, "noise_lambda": FLOATS,
                       "seed": U32S},
        ReportPickOutcome: {"estimate_id": U64S, "picked": BOOLS},
    }[srv_type]


def missing_fields(srv_type: Any) -> list[str]:
    """Fields of the request that the table does not cover (empty when complete)."""
    return sorted(set(_fields(srv_type.Request)) - set(table(srv_type)))


def cases(srv_type: Any, base: Callable[[], Any]) -> tuple[list[tuple[str, Any]], list[tuple[str, str]]]:
    """(label, request) for every boundary value of every field, each on a fresh `base()`; and
    (label, rclpy's refusal) for the values the field's type cannot hold."""
    sendable: list[tuple[str, Any]] = []
    unsendable: list[tuple[str, str]] = []
    kinds = _fields(srv_type.Request)
    for path, values in table(srv_type).items():
        for value in values:
            req = base()
            _set(req, path, value)
            sendable.append((f"{path}={_short(value)}", req))
        kind = kinds[path]
        for value in UNSENDABLE.get(kind, ()) if not kind.startswith("sequence") else ():
            unsendable.append((f"{path}={_short(value)}", _client_side(srv_type, base(), path, value, kind)))
    return sendable, unsendable


def _client_side(srv_type: Any, req: Any, path: str, value: Any, kind: str) -> str:
    """What rclpy does with a value the field's type cannot hold: refuses it (building or
    serialising the request) or wraps it into the type's range; never sends it as it is."""
    from rclpy.serialization import deserialize_message, serialize_message

    try:
        _set(req, path, value)
        data = serialize_message(req)
    except (AssertionError, TypeError, ValueError, OverflowError, SystemError) as exc:
        return f"refused by rclpy: {type(exc).__name__}"
    got = deserialize_message(data, srv_type.Request)
    for name in path.split("."):
        got = getattr(got, name)
    low, high = RANGES[kind]
    assert low <= got <= high and got != value, f"{path}={value!r} reached the wire as {got!r}"
    return f"wrapped by rclpy to {got}"


RANGES = {"uint32": (0, U32), "uint64": (0, U64), "int32": (-2**31, I32)}


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 30 else f"{text[:20]}... ({len(value)} long)"
