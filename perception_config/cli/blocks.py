"""`perception-config blocks`: the building blocks with their parameters."""
from __future__ import annotations

import argparse


def _cmd_blocks(args: argparse.Namespace) -> int:
    from ..blocks import load_all

    for name, cls in sorted(load_all().items()):
        print(f"{name}  ({cls.kind.value}; inputs: {', '.join(cls.inputs)})")
        doc = (cls.__doc__ or "").strip().splitlines()
        if doc:
            print(f"    {doc[0]}")
        for p in cls.params:
            rng = f" in {list(p.choices)}" if p.choices else (f" in [{p.low}, {p.high}]" if p.low is not None else "")
            print(f"    {p.name} = {p.default!r}{rng}  {p.doc}")
        if cls.score_names:
            print(f"    scores: {', '.join(cls.score_names)}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    bl = sub.add_parser("blocks", help="list the building blocks with their parameters")
    bl.set_defaults(func=_cmd_blocks)
