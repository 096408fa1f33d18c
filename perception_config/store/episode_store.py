"""The episode store: every episode training, evaluation or the configurator plays, in SQLite.

One file (`episodes.sqlite` in a run folder) with two tables, `episodes` (one row per episode:
where it came from, the policy that played it, its object and frame, lambda, generator, outcome,
time) and `steps` (one row per operator: step 0 is reset's initial hypothesis, 1.. the actions,
each with its scores, the hypothesis after it and, for a pick that ran, the pick's result as the
simulation or the robot reported it), plus `pick_outcomes` (external pick reports, see
`record_pick_outcome`). Column names are a contract (consumers code against them): columns may be
added, never renamed; a change that old readers cannot read raises SCHEMA_VERSION.
An episode comes as an `EpisodeRecord` (store/episode_record.py); a step's pose is stored as the
JSON of core/pose_json.py.

Guarantees:
- one transaction per episode (its row and all its step rows): a reader sees a whole episode or
  none of it;
- WAL journal, `synchronous=NORMAL` by default: a committed episode is in the WAL file before
  `append` returns, so it survives SIGKILL of the writer (the OS keeps the file); a power cut may
  lose the last commits but never corrupts the file. `synchronous="FULL"` also fsyncs every
  commit (power-cut durable, about 1-10 ms more per episode): the configurator uses it (a robot
  pick is worth far more than the fsync), training the default (thousands of episodes);
- `PRAGMA application_id` marks the file as an episode store and `PRAGMA user_version` holds the
  schema version: a file that is not SQLite, a foreign SQLite database, a corrupt one or one from
  a newer schema is refused with an error naming the file (EpisodeStoreError), never altered;
- `busy_timeout`: a writer waits for another process's transaction instead of failing at once.
Callers that must never stop for the store (training, the configurator) go through
`StoreWriter`, which logs one line per failed append and goes on.
"""
from __future__ import annotations

import json
import math
import os
import sqlite3
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from ..core.pose_json import pose_arrays, pose_json
from .episode_record import EpisodeRecord, record_from_trajectory

if TYPE_CHECKING:
    from ..rl.episode_loop import Trajectory

SCHEMA_VERSION = 1
APPLICATION_ID = 0x50434553  # "PCES": perception_config episode store
STORE_NAME = "episodes.sqlite"  # the file's name in a run folder
BUSY_TIMEOUT_S = 5.0
SQLITE_MAGIC = b"SQLite format 3\x00"
PICK_SOURCES = ("simulated", "robot")
# An episode's label: "ground_truth" (its frame's ground truth judged the picks: a simulation, a
# dataset replayed), "robot" (the robot's own pick outcomes: a cell), "none" (no pick has an outcome).
LABEL_KINDS = ("ground_truth", "robot", "none")

EPISODE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("id", "INTEGER PRIMARY KEY"), ("source", "TEXT NOT NULL"), ("created", "REAL NOT NULL"),
    ("policy_version", "TEXT"), ("agent", "TEXT"), ("dataset", "TEXT"), ("scene_id", "INTEGER"),
    ("im_id", "INTEGER"), ("obj_id", "INTEGER"), ("frame_stamp_ns", "INTEGER"), ("noise_lambda", "REAL"),
    ("generator", "TEXT"), ("episode_seed", "INTEGER"), ("success", "INTEGER"), ("first_pick_success", "INTEGER"),
    ("time_s", "REAL"), ("cost", "REAL"), ("steps", "INTEGER"), ("stopped", "INTEGER"),
    ("label", "TEXT"),  # what judges its picks: LABEL_KINDS (added to schema 1; older files gain it on open)
)
STEP_COLUMNS: tuple[tuple[str, str], ...] = (
    ("episode_id", "INTEGER NOT NULL REFERENCES episodes(id)"), ("step", "INTEGER NOT NULL"), ("action", "TEXT"),
    ("ok", "INTEGER"), ("seconds", "REAL"), ("operation_seconds", "REAL"), ("scores", "TEXT"), ("pose", "TEXT"),
    ("picked", "INTEGER"), ("pick_source", "TEXT"),
)
OUTCOME_COLUMNS: tuple[tuple[str, str], ...] = (
    ("episode_id", "INTEGER NOT NULL"), ("step", "INTEGER NOT NULL"), ("picked", "INTEGER NOT NULL"),
    ("source", "TEXT NOT NULL"), ("created", "REAL NOT NULL"), ("previous_picked", "INTEGER"),
    ("previous_source", "TEXT"),
)
TABLES = {"episodes": EPISODE_COLUMNS, "steps": STEP_COLUMNS, "pick_outcomes": OUTCOME_COLUMNS}
_SCHEMA = [
    f"CREATE TABLE episodes ({', '.join(f'{n} {t}' for n, t in EPISODE_COLUMNS)})",
    f"CREATE TABLE steps ({', '.join(f'{n} {t}' for n, t in STEP_COLUMNS)}, PRIMARY KEY (episode_id, step))",
    f"CREATE TABLE pick_outcomes ({', '.join(f'{n} {t}' for n, t in OUTCOME_COLUMNS)}, "
    "PRIMARY KEY (episode_id, step))",
    "CREATE INDEX episodes_source ON episodes (source, agent)",
]


class EpisodeStoreError(ValueError):
    """A store that cannot be used (not SQLite, foreign, corrupt, newer schema) or a refused
    write (unknown episode or step, duplicated outcome); the message names the file."""


def _finite(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def scores_json(scores: dict[str, float]) -> str:
    """The scores as JSON; a non-finite score (NaN: not computed) is stored as null."""
    return json.dumps({str(k): _finite(v) for k, v in scores.items()}, allow_nan=False)


# -- the store ---------------------------------------------------------------------------------
class EpisodeStore:
    """An episode store file, opened (and created when absent or empty) for appending and reading.

    Thread-safe (one connection behind a lock): the configurator appends from its worker thread.
    `synchronous` is "NORMAL" (survives a killed process) or "FULL" (also a power cut).
    """

    def __init__(self, path: str | os.PathLike, *, synchronous: str = "NORMAL",
                 busy_timeout: float = BUSY_TIMEOUT_S, readonly: bool = False) -> None:
        if synchronous not in ("NORMAL", "FULL"):
            raise ValueError(f"synchronous must be NORMAL or FULL, got {synchronous!r}")
        self.path = Path(path)
        self._lock = threading.Lock()
        exists = self.path.exists() and self.path.stat().st_size > 0
        if readonly and not exists:
            raise EpisodeStoreError(f"episode store {self.path} does not exist (or is empty)")
        if exists:
            _check_header(self.path)
        elif not readonly:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        uri = f"file:{self.path.resolve()}?mode={'ro' if readonly else 'rwc'}"
        try:
            self._db = sqlite3.connect(uri, uri=True, timeout=busy_timeout, isolation_level=None,
                                       check_same_thread=False)
        except sqlite3.Error as exc:
            raise EpisodeStoreError(f"cannot open episode store {self.path}: {exc}") from None
        try:
            self._db.execute(f"PRAGMA busy_timeout = {int(busy_timeout * 1000)}")
            self._open(exists, readonly, synchronous)
        except sqlite3.DatabaseError as exc:
            self._db.close()
            raise EpisodeStoreError(f"episode store {self.path} is not readable ({exc}): is it corrupt? "
                                    "Nothing was changed; move it aside to start a new store") from None
        except BaseException:
            self._db.close()
            raise

    def _open(self, exists: bool, readonly: bool, synchronous: str) -> None:
        app_id = self._db.execute("PRAGMA application_id").fetchone()[0]
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if app_id == 0 and version == 0 and not tables and not readonly:
            self._create()
        elif app_id != APPLICATION_ID:
            what = f"tables {sorted(tables)[:8]}" if tables else "no tables"
            raise EpisodeStoreError(f"{self.path} is an SQLite database but not a perception_config episode store "
                                    f"(application_id {app_id:#x}, {what}): refusing to use it")
        elif version > SCHEMA_VERSION:
            raise EpisodeStoreError(f"episode store {self.path} has schema version {version}, newer than this "
                                    f"perception_config reads ({SCHEMA_VERSION}): update perception_config")
        elif version < 1:
            raise EpisodeStoreError(f"episode store {self.path} has an unknown schema version {version}")
        else:
            missing = [t for t in TABLES if t not in tables]
            if missing:
                raise EpisodeStoreError(f"episode store {self.path} (schema {version}) lacks tables {missing}: "
                                        "is it corrupt?")
        if not readonly:
            self._add_missing_columns()
            mode = self._db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            self.journal_mode = str(mode).lower()
            self._db.execute(f"PRAGMA synchronous = {synchronous}")
        else:
            self.journal_mode = str(self._db.execute("PRAGMA journal_mode").fetchone()[0]).lower()
        self.schema_version = SCHEMA_VERSION if not exists else int(version)

    def _add_missing_columns(self) -> None:
        """Columns added to schema 1 after a file was made (e.g. `label`), added to that file: old
        readers ignore them, new ones find them (NULL in the old rows)."""
        for table, columns in TABLES.items():
            have = {r[1] for r in self._db.execute(f"PRAGMA table_info({table})")}
            for name, sql_type in columns:
                if name not in have:
                    self._db.execute(f"ALTER TABLE {table} ADD COLUMN {name} {sql_type}")

    def has_column(self, table: str, name: str) -> bool:
        """Whether `table` has the column (a read-only store made before the column was added may not)."""
        with self._lock:
            return any(r[1] == name for r in self._db.execute(f"PRAGMA table_info({table})"))

    def _create(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            for sql in _SCHEMA:
                self._db.execute(sql)
            self._db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            self._db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise

    # -- writing -------------------------------------------------------------------------------
    def append(self, record: EpisodeRecord) -> int:
        """Store one episode and its steps in one transaction; its id. Raises sqlite3.Error /
        OSError as SQLite reports them (a full disk, a lock held past busy_timeout); the store
        is then as it was before the call."""
        names = [n for n, _ in EPISODE_COLUMNS if n != "id"]
        # the `steps` column counts the actions (step 0, the initial hypothesis, is not one)
        row = [sum(1 for s in record.steps if s.step > 0) if n == "steps" else _sql_value(getattr(record, n))
               for n in names]
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                cur = self._db.execute(f"INSERT INTO episodes ({', '.join(names)}) "
                                       f"VALUES ({', '.join('?' * len(names))})", row)
                eid = int(cur.lastrowid)
                self._db.executemany(
                    "INSERT INTO steps VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    [(eid, int(s.step), s.action, int(bool(s.ok)), _finite(s.seconds), _finite(s.operation_seconds),
                      scores_json(s.scores), None if s.pose is None else json.dumps(pose_json(s.pose)),
                      None if s.picked is None else int(bool(s.picked)), s.pick_source) for s in record.steps])
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
        return eid

    def record_pick_outcome(self, episode_id: int, step: int, picked: bool, source: str) -> None:
        """Store a pick's result reported after the episode (a robot that tried the pick). The
        step's `picked`/`pick_source` become the report; the former values are kept in
        `pick_outcomes`; an episode labelled "none" becomes labelled "robot" by a robot's report.
        Refused (EpisodeStoreError, nothing changed): an unknown episode or step, a step that
        already has a reported outcome, an unknown source."""
        if source not in PICK_SOURCES:
            raise EpisodeStoreError(f"pick outcome source must be one of {PICK_SOURCES}, got {source!r}")
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                if self._db.execute("SELECT 1 FROM episodes WHERE id = ?", (int(episode_id),)).fetchone() is None:
                    raise EpisodeStoreError(f"episode store {self.path}: no episode {episode_id}: "
                                            "an outcome for an unknown estimate is refused")
                row = self._db.execute("SELECT picked, pick_source FROM steps WHERE episode_id = ? AND step = ?",
                                       (int(episode_id), int(step))).fetchone()
                if row is None:
                    raise EpisodeStoreError(f"episode store {self.path}: episode {episode_id} has no step {step}")
                if self._db.execute("SELECT 1 FROM pick_outcomes WHERE episode_id = ? AND step = ?",
                                    (int(episode_id), int(step))).fetchone() is not None:
                    raise EpisodeStoreError(f"episode store {self.path}: episode {episode_id} step {step} already has "
                                            "a reported pick outcome: a duplicated outcome is refused")
                self._db.execute("INSERT INTO pick_outcomes VALUES (?, ?, ?, ?, ?, ?, ?)",
                                 (int(episode_id), int(step), int(bool(picked)), source, time.time(), row[0], row[1]))
                self._db.execute("UPDATE steps SET picked = ?, pick_source = ? WHERE episode_id = ? AND step = ?",
                                 (int(bool(picked)), source, int(episode_id), int(step)))
                if source == "robot":
                    self._db.execute("UPDATE episodes SET label = 'robot' WHERE id = ? AND "
                                     "(label IS NULL OR label = 'none')", (int(episode_id),))
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def _rollback(self) -> None:
        try:
            self._db.execute("ROLLBACK")
        except sqlite3.Error:  # SQLite already rolled back (e.g. SQLITE_FULL)
            pass

    # -- reading -------------------------------------------------------------------------------
    def query(self, sql: str, params: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            return self._db.execute(sql, params).fetchall()

    def count(self, table: str = "episodes") -> int:
        if table not in TABLES:
            raise ValueError(f"unknown table {table!r}; tables: {', '.join(TABLES)}")
        return int(self.query(f"SELECT COUNT(*) FROM {table}")[0][0])

    def iter_rows(self, table: str) -> tuple[list[str], Iterator[tuple[Any, ...]]]:
        """Column names and the raw rows of `table` (JSON columns as text), in key order."""
        if table not in TABLES:
            raise ValueError(f"unknown table {table!r}; tables: {', '.join(TABLES)}")
        order = "id" if table == "episodes" else "episode_id, step"
        with self._lock:
            cur = self._db.execute(f"SELECT * FROM {table} ORDER BY {order}")
            names = [d[0] for d in cur.description]
            rows = cur.fetchall()
        return names, iter(rows)

    def iter_steps(self, where: str | None = None, params: tuple[Any, ...] = ()) -> Iterator[dict[str, Any]]:
        """Every step with its episode's columns prefixed `episode_` (scores and pose decoded:
        pose {"R": (3, 3), "t": (3,)} or None). `where`: an SQL condition on the columns `s.*`
        (steps) and `e.*` (episodes), e.g. "e.source = ? AND s.step > 0" with `params`."""
        ep_cols = [n for n, _ in EPISODE_COLUMNS]
        sql = (f"SELECT s.*, {', '.join(f'e.{n}' for n in ep_cols)} FROM steps s JOIN episodes e "
               f"ON e.id = s.episode_id{' WHERE ' + where if where else ''} ORDER BY s.episode_id, s.step")
        with self._lock:
            cur = self._db.execute(sql, params)
            names = [d[0] for d in cur.description][:len(STEP_COLUMNS)] + [f"episode_{n}" for n in ep_cols]
            rows = cur.fetchall()
        for row in rows:
            d = dict(zip(names, row))
            d["scores"] = json.loads(d["scores"]) if d["scores"] else {}
            d["pose"] = None if d["pose"] is None else pose_arrays(json.loads(d["pose"]))
            yield d

    def integrity(self) -> str:
        """SQLite's quick_check: "ok" or what is wrong."""
        return "; ".join(str(r[0]) for r in self.query("PRAGMA quick_check"))

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> EpisodeStore:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _sql_value(v: Any) -> Any:
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _finite(v)
    return v


def _check_header(path: Path) -> None:
    """Refuse a file that is not SQLite before SQLite sees it (it would say only "file is not a
    database", and a writer must not touch a foreign file)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(SQLITE_MAGIC))
    except OSError as exc:
        raise EpisodeStoreError(f"cannot read episode store {path}: {exc}") from None
    if head != SQLITE_MAGIC:
        raise EpisodeStoreError(f"{path} is not an episode store: not an SQLite database file")


# -- writing that never stops the caller -------------------------------------------------------------
class StoreWriter:
    """Appends episodes for a caller that must go on whatever happens to the store (training,
    evaluation, the configurator): every failure (a store that cannot be opened, a full disk, a
    lock held too long, a corrupt file) is one line through `log` and the episode is dropped;
    the next episode tries again (opening included). Repeated failures with the same message
    are logged at the 1st, 10th, 100th, ... time, with the count."""

    def __init__(self, path: str | os.PathLike, log: Callable[[str], None], *, synchronous: str = "NORMAL",
                 busy_timeout: float = BUSY_TIMEOUT_S) -> None:
        self.path = Path(path)
        self.log = log
        self.synchronous = synchronous
        self.busy_timeout = busy_timeout
        self.store: EpisodeStore | None = None
        self.appended = 0
        self.failed = 0
        self._last_error = ""
        self._repeats = 0
        self.append_seconds = 0.0  # total time spent in append (for the cost report)

    def open(self) -> bool:
        """Open (or create) the store now, so that a bad path is reported at start-up; False
        (logged) when it cannot be opened: appends try again."""
        try:
            self._ensure_open()
        except (sqlite3.Error, OSError, ValueError) as exc:
            self._report(exc)
            return False
        return True

    def _ensure_open(self) -> EpisodeStore:
        if self.store is None:
            self.store = EpisodeStore(self.path, synchronous=self.synchronous, busy_timeout=self.busy_timeout)
        return self.store

    def append(self, record: EpisodeRecord) -> int | None:
        """The stored episode's id, or None when it could not be stored (logged)."""
        start = time.perf_counter()
        try:
            eid = self._ensure_open().append(record)
        except (sqlite3.Error, OSError, ValueError) as exc:  # EpisodeStoreError is a ValueError
            self.failed += 1
            self._report(exc)
            if isinstance(exc, EpisodeStoreError):
                self.close()  # reopened (and checked again) for the next episode
            return None
        finally:
            self.append_seconds += time.perf_counter() - start
        self.appended += 1
        return eid

    def _report(self, exc: BaseException) -> None:
        msg = str(exc)
        self._repeats = self._repeats + 1 if msg == self._last_error else 1
        self._last_error = msg
        if self._repeats == 1 or math.log10(self._repeats).is_integer():
            times = f" ({self._repeats} times in a row)" if self._repeats > 1 else ""
            self.log(f"episode store {self.path}: episode not stored{times}: {type(exc).__name__}: {msg}")

    def summary(self) -> str:
        n = self.appended + self.failed
        mean = f", {1000 * self.append_seconds / n:.2f} ms per append" if n else ""
        return f"{self.appended} episodes appended to {self.path}, {self.failed} not stored{mean}"

    def close(self) -> None:
        if self.store is not None:
            try:
                self.store.close()
            except sqlite3.Error:
                pass
            self.store = None


def store_episode(writer: StoreWriter, traj: Trajectory, *, image_ids: bool = True, label: str | None = None,
                  **context: Any) -> int | None:
    """Append a played episode through `writer` (context: record_from_trajectory's keywords);
    never raises: whatever goes wrong is one line of the writer's log. `image_ids=False`: the
    episode's scene and image ids are placeholders (the configurator knows the frame by its
    stamp only) and are stored as NULL. `label`: its label kind when the caller knows better
    than its picks tell (episode_record.pick_label)."""
    try:
        record = record_from_trajectory(traj, **context)
    except Exception as exc:  # noqa: BLE001  (the caller must go on; the episode is reported lost)
        writer.failed += 1
        writer._report(exc)
        return None
    if not image_ids:
        record.scene_id = record.im_id = None
    if label is not None:
        record.label = label
    return writer.append(record)


def policy_version(path: str | os.PathLike) -> str:
    """A policy file's version for the store: "sha256:<first 16 hex>" of its content checksum
    (policy_io.content_checksum, recorded in the file), else of the file's bytes."""
    from ..agents.policy_io import read_file
    from ..util.checksum import CHECKSUM_KEY

    try:
        meta, _ = read_file(path)
        digest = str(meta.get(CHECKSUM_KEY) or "")
    except Exception:  # noqa: BLE001  (a version label must not stop the caller; the policy loader reports)
        digest = ""
    if not digest:
        import hashlib

        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return f"sha256:{digest[:16]}"
