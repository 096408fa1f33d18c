"""Generate `ros2msg_schemas.py`: the ros2msg schema texts the MCAP writer ships.

A rosbag2 MCAP file stores, per message type, the *complete message definition* in `ros2msg`
encoding (rosbag2 docs/message_definition_encoding.md): the type's .msg text, then for every type
it depends on (recursively, each once) a line of 80 `=`, a line `MSG: pkg/Name` and that type's
.msg text. This module rebuilds those texts exactly the way rosbag2_cpp's
LocalMessageDefinitionSource does (dependencies of each definition in sorted order, depth first),
from the .msg files of an installed ROS prefix (`<prefix>/share/<pkg>/msg/*.msg`, the PyPI ROS
wheels put them in the venv root) and, for our own interfaces, from the repository's msg_defs/.

The generated module is what runs in an installed package (msg_defs/ may not be next to the
code there); test/test_bag.py checks it still equals what the .msg files on disk give.

Regenerate after changing msg_defs/:  python -m perception_config.datasets.ros2msg_gen
"""
from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

from ..atomic_file import atomic_write

# The types the bag writer needs, plus our other messages (a recorder of the nodes' outputs).
TYPES = (
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
    "std_msgs/msg/String",
    "perception_config_interfaces/msg/ObjectPoses",
    "perception_config_interfaces/msg/Hypothesis",
    "perception_config_interfaces/msg/OperatorTrace",
)
INTERFACES_PACKAGE = "perception_config_interfaces"
REPO_MSG_DEFS = Path(__file__).resolve().parents[2] / "msg_defs"
GENERATED = Path(__file__).resolve().parent / "ros2msg_schemas.py"
DELIMITER = "=" * 80 + "\n"
LINE_LENGTH = 120  # ruff.toml's line-length: the generated module is linted like the rest

# rosbag2_cpp: first token of each line that is not a primitive type (arrays stripped).
_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string",
}


class MsgNotFoundError(FileNotFoundError):
    pass


def share_dirs() -> list[Path]:
    """ROS prefixes' share/ folders: AMENT_PREFIX_PATH entries, then this interpreter's prefix."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    out: list[Path] = []
    for p in prefixes:
        d = Path(p) / "share"
        if d.is_dir() and d not in out:
            out.append(d)
    return out


def find_msg(pkg: str, name: str, ext: str = ".msg") -> Path:
    """The .msg (or .json type description) file of pkg/msg/name; msg_defs/ for our package."""
    candidates = []
    if pkg == INTERFACES_PACKAGE and ext == ".msg":
        candidates.append(REPO_MSG_DEFS / "msg" / f"{name}{ext}")
    candidates += [d / pkg / "msg" / f"{name}{ext}" for d in share_dirs()]
    for c in candidates:
        if c.is_file():
            return c
    raise MsgNotFoundError(f"no {pkg}/msg/{name}{ext} in {[str(c.parent) for c in candidates]}")


def _split(type_name: str) -> tuple[str, str]:
    parts = type_name.split("/")
    if len(parts) == 2:
        return parts[0], parts[1]
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    raise ValueError(f"not a message type name: {type_name!r}")


def dependencies(text: str, package: str) -> list[str]:
    """Sorted non-primitive field types of a .msg text, as rosbag2 names them (pkg/Name)."""
    deps = set()
    for m in _FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{package}/{t}")
    return sorted(deps)


def full_text(type_name: str) -> str:
    """The complete ros2msg definition of `type_name` (e.g. sensor_msgs/msg/Image)."""
    seen: set[str] = set()

    def rec(name: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f"message definition of {type_name} nests too deep")
        pkg, short = _split(name)
        text = find_msg(pkg, short).read_text(encoding="utf-8")
        out = text
        for dep in dependencies(text, pkg):
            if dep not in seen:
                seen.add(dep)
                out += "\n" + DELIMITER + f"MSG: {dep}\n" + rec(dep, depth - 1)
        return out

    return rec(type_name, 50)


def type_hash(type_name: str) -> str:
    """RIHS01 type hash: from the installed type description (.json), else computed by rosbags."""
    pkg, short = _split(type_name)
    try:
        desc = json.loads(find_msg(pkg, short, ".json").read_text())
        for h in desc["type_hashes"]:
            if h["type_name"] == f"{pkg}/msg/{short}":
                return h["hash_string"]
    except MsgNotFoundError:
        pass
    return rihs01_with_rosbags(type_name)


def rihs01_with_rosbags(type_name: str) -> str:
    """RIHS01 hash computed by rosbags (a dev/test dependency) from the .msg files on disk."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    todo, done, types = [type_name], set(), {}
    while todo:
        name = todo.pop()
        if name in done:
            continue
        done.add(name)
        pkg, short = _split(name)
        text = find_msg(pkg, short).read_text(encoding="utf-8")
        types.update(get_types_from_msg(text, f"{pkg}/msg/{short}"))
        todo += [f"{_split(d)[0]}/msg/{_split(d)[1]}" for d in dependencies(text, pkg)]
    store.register(types)
    return store.hash_rihs01(f"{_split(type_name)[0]}/msg/{_split(type_name)[1]}")


def _pieces(line: str, width: int) -> list[str]:
    """`line` cut, after spaces where it can be, into pieces whose repr is at most `width` long
    (adjacent string literals: the value is the same, the module keeps to the line length)."""
    pieces: list[str] = []
    for token in re.split(r"(?<= )(?=\S)", line):
        if pieces and len(repr(pieces[-1] + token)) <= width:
            pieces[-1] += token
            continue
        while len(repr(token)) > width and len(token) > 1:  # a word longer than the width: cut it
            cut = len(token) - 1
            while cut > 1 and len(repr(token[:cut])) > width:
                cut -= 1
            pieces.append(token[:cut])
            token = token[cut:]
        pieces.append(token)
    return pieces


def _literal(text: str, indent: str) -> str:
    lines = text.splitlines(keepends=True) or [""]
    pad = f"{indent}    "
    pieces = [piece for line in lines for piece in _pieces(line, LINE_LENGTH - len(pad))]
    return "(\n" + "".join(f"{pad}{piece!r}\n" for piece in pieces) + f"{indent})"


def render_module(types: tuple[str, ...] = TYPES) -> str:
    out = [
        '"""ros2msg schema texts and RIHS01 type hashes of the messages the MCAP bags carry.\n',
        "\n",
        "GENERATED by `python -m perception_config.datasets.ros2msg_gen` from the .msg files (ROS\n",
        "prefix share/ and the repository's msg_defs/); do not edit. test/test_bag.py checks it.\n",
        '"""\n',
        "\n",
        "SCHEMAS: dict[str, str] = {\n",
    ]
    for t in types:
        out.append(f"    {t!r}: {_literal(full_text(t), '    ')},\n")
    out.append("}\n\nTYPE_HASHES: dict[str, str] = {\n")
    for t in types:
        key, value = repr(t), repr(type_hash(t))
        entry = f"    {key}: {value},"
        if len(entry) > LINE_LENGTH:  # the hash on a line of its own
            entry = f"    {key}:\n        {value},"
        out.append(entry + "\n")
    out.append("}\n")
    return "".join(out)


def main() -> int:
    text = render_module()
    atomic_write(GENERATED, text)
    print(f"wrote {GENERATED} ({len(TYPES)} types)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
