"""The one parser of object ids, stamps and method lists every node uses (no ROS needed)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from perception_config.ros.request_fields import (
    MAX_METHODS,
    MAX_OBJECT_ID,
    excerpt,
    parse_methods,
    parse_object_id,
    parse_stamp,
)


@pytest.mark.parametrize("text", ["1", "0", "15", "123456", "9" * MAX_OBJECT_ID])
def test_canonical_object_ids_are_accepted_as_they_are(text):
    assert parse_object_id(text) == text


@pytest.mark.parametrize("text, expected", [
    ("", "empty"), (" 1", "not an integer"), ("1 ", "not an integer"), ("+1", "not an integer"),
    ("-1", "not an integer"), ("\u0661", "not an integer"), ("1\n", "not an integer"), ("1.0", "not an integer"),
    ("0x1", "not an integer"), ("01", "leading zeros (write 1)"), ("0" * 40 + "1", "leading zeros"),
    ("00", "leading zeros (write 0)"), ("1" * (MAX_OBJECT_ID + 1), "characters long"), (1, "must be text"),
])
def test_other_object_ids_are_refused_naming_why(text, expected):
    with pytest.raises(ValueError, match="object_id") as err:
        parse_object_id(text)
    assert expected in str(err.value)


def test_a_huge_id_is_quoted_by_a_short_prefix_only():
    with pytest.raises(ValueError) as err:
        parse_object_id("x" * 1_000_000)
    assert len(str(err.value)) < 200 and "1000000 characters" in str(err.value)
    assert excerpt("abc") == "'abc'" and excerpt("a" * 50).endswith("... (50 characters)")


def stamp(sec, nanosec):
    return SimpleNamespace(sec=sec, nanosec=nanosec)


def test_stamps_are_nanoseconds_and_nothing_aliases_another_second():
    assert parse_stamp(stamp(0, 0)) == 0
    assert parse_stamp(stamp(1_700_000_000, 999_999_999)) == 1_700_000_000_999_999_999
    with pytest.raises(ValueError, match=r"frame.stamp.nanosec must be in 0..999999999, got 1000000000"):
        parse_stamp(stamp(1, 1_000_000_000), "frame.stamp")
    with pytest.raises(ValueError, match="sec is negative"):
        parse_stamp(stamp(-1, 0))


def test_method_lists_are_bounded_and_each_method_named_once():
    assert parse_methods([]) == [] and parse_methods(["psi_c", "psi_d"]) == ["psi_c", "psi_d"]
    with pytest.raises(ValueError, match=f"20000 methods requested \\(at most {MAX_METHODS}\\)"):
        parse_methods(["psi_c"] * 20000)
    with pytest.raises(ValueError, match="'psi_c' is requested twice"):
        parse_methods(["psi_c", "psi_d", "psi_c"])
    with pytest.raises(ValueError, match="characters long") as err:
        parse_methods(["m" * 100_000])
    assert len(str(err.value)) < 200
