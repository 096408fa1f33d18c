"""`perception-config episodes info | export`: a run's episode store, summarised or exported."""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _cmd_episodes_info(args: argparse.Namespace) -> int:
    from ..store.report import format_info, store_info

    info = store_info(args.store)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(format_info(info))
    return 0


def _cmd_episodes_export(args: argparse.Namespace) -> int:
    from ..store.report import export_table

    n = export_table(args.store, args.out, args.table)
    print(f"wrote {n} rows of {args.table} to {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    ep = sub.add_parser("episodes", help="the episode store (episodes.sqlite of a run): summary and export")
    epsub = ep.add_subparsers(dest="episodes_command", required=True)
    ei = epsub.add_parser("info", help="schema version, size, episodes per source/agent and per object with the "
                          "success share and mean time")
    ei.add_argument("store", type=Path, help="an episodes.sqlite file")
    ei.add_argument("--json", action="store_true", help="print the summary as JSON")
    ei.set_defaults(func=_cmd_episodes_info)
    ee = epsub.add_parser("export", help="write a table of the store as CSV or Parquet (by --out's suffix)")
    ee.add_argument("store", type=Path, help="an episodes.sqlite file")
    ee.add_argument("--out", type=Path, required=True, help="FILE.csv or FILE.parquet (written atomically)")
    ee.add_argument("--table", choices=("episodes", "steps", "pick_outcomes"), default="episodes")
    ee.set_defaults(func=_cmd_episodes_export)
