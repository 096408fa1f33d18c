"""`perception-config episodes info|export`: what an episode store holds, and its tables as files.

`store_info` summarises a store (store/episode_store.py): schema version, file sizes, counts per
source and agent and per object with the success share and mean time. `export_table` writes one
table as CSV (JSON columns as their text) or Parquet (through pyarrow, imported only here, with
the SQL column types), atomically (atomic_file): a reader never sees half a file.
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import Any

from ..util.atomic_file import atomic_output, atomic_write
from .episode_store import TABLES, EpisodeStore

EXPORT_FORMATS = (".csv", ".parquet")


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def store_info(path: str | os.PathLike) -> dict[str, Any]:
    """Schema, sizes and counts of a store (opened read-only; EpisodeStoreError if unusable)."""
    path = Path(path)
    with EpisodeStore(path, readonly=True) as store:
        groups = store.query(
            "SELECT source, agent, COUNT(*), AVG(success), AVG(time_s), COUNT(DISTINCT policy_version) "
            "FROM episodes GROUP BY source, agent ORDER BY source, agent")
        objects = store.query("SELECT obj_id, COUNT(*), AVG(success), AVG(time_s) FROM episodes "
                              "GROUP BY obj_id ORDER BY obj_id")
        span = store.query("SELECT MIN(created), MAX(created) FROM episodes")[0]
        info = {
            "path": str(path), "schema_version": store.schema_version, "journal_mode": store.journal_mode,
            "file_bytes": _size(path), "wal_bytes": _size(path.with_name(path.name + "-wal")),
            "episodes": store.count("episodes"), "steps": store.count("steps"),
            "pick_outcomes": store.count("pick_outcomes"), "first_created": span[0], "last_created": span[1],
            "by_source_agent": [{"source": s, "agent": a, "episodes": n, "success": sr, "mean_time_s": t,
                                 "policy_versions": pv} for s, a, n, sr, t, pv in groups],
            "by_object": [{"obj_id": o, "episodes": n, "success": sr, "mean_time_s": t} for o, n, sr, t in objects],
        }
    return info


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def format_info(info: dict[str, Any]) -> str:
    """The info as a few lines and two small tables."""
    mb = 1024 * 1024
    lines = [f"episode store {info['path']}",
             f"  schema version {info['schema_version']}, journal {info['journal_mode']}, "
             f"{info['file_bytes'] / mb:.2f} MiB (+ WAL {info['wal_bytes'] / mb:.2f} MiB)",
             f"  {info['episodes']} episodes, {info['steps']} steps (initial hypotheses included), "
             f"{info['pick_outcomes']} reported pick outcomes"]
    if info["episodes"]:
        import time

        fmt = "%Y-%m-%d %H:%M:%S"
        lines.append(f"  from {time.strftime(fmt, time.gmtime(info['first_created']))} to "
                     f"{time.strftime(fmt, time.gmtime(info['last_created']))} UTC")
    rows = [("source", "agent", "episodes", "success", "mean time s", "policy versions")]
    rows += [(g["source"], str(g["agent"]), str(g["episodes"]), _num(g["success"], ".3f"),
              _num(g["mean_time_s"], ".3f"), str(g["policy_versions"])) for g in info["by_source_agent"]]
    lines += ["", *_table(rows, left=2)]
    rows = [("object", "episodes", "success", "mean time s")]
    rows += [(str(o["obj_id"]), str(o["episodes"]), _num(o["success"], ".3f"), _num(o["mean_time_s"], ".3f"))
             for o in info["by_object"]]
    lines += ["", *_table(rows, left=1)]
    return "\n".join(lines)


def _table(rows: list[tuple[str, ...]], left: int) -> list[str]:
    """Aligned columns: the first `left` to the left (names), the rest to the right (numbers)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in rows]


def export_table(path: str | os.PathLike, out: str | os.PathLike, table: str = "episodes") -> int:
    """Write `table` of the store at `path` to `out` (.csv or .parquet); the number of rows."""
    out = Path(out)
    if out.suffix.lower() not in EXPORT_FORMATS:
        raise ValueError(f"cannot export to {out}: the file name must end in {' or '.join(EXPORT_FORMATS)}")
    if table not in TABLES:
        raise ValueError(f"unknown table {table!r}; tables: {', '.join(TABLES)}")
    with EpisodeStore(path, readonly=True) as store:
        names, rows = store.iter_rows(table)
        rows = list(rows)
    if out.suffix.lower() == ".csv":
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(names)
        w.writerows(rows)
        atomic_write(out, buf.getvalue())
    else:
        _write_parquet(out, table, names, rows)
    return len(rows)


def _write_parquet(out: Path, table: str, names: list[str], rows: list[tuple[Any, ...]]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    declared = dict(TABLES[table])
    types = {"INTEGER": pa.int64(), "REAL": pa.float64(), "TEXT": pa.string()}

    def arrow_type(name: str) -> Any:  # columns added after this version: let pyarrow infer
        decl = declared.get(name)
        return types.get(decl.split()[0]) if decl else None

    columns = {n: pa.array([r[i] for r in rows], type=arrow_type(n)) for i, n in enumerate(names)}
    with atomic_output(out) as tmp:
        pq.write_table(pa.table(columns), tmp)
