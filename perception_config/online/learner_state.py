"""The learner's state as a file: `<learn_dir>/learner_state.json`, for anyone watching the cell.

The learner process (policy_learner.run_learner) rewrites it atomically when it starts, when a
cycle begins and when a cycle ends:

| key | meaning |
|---|---|
| `state` | `idle` (waiting for `every` new stored estimates) or `training` (a cycle runs) |
| `stored` | stored estimates when the learner started, or when the last cycle began |
| `every` | new stored estimates between two cycles (the configurator's `learn_every`) |
| `cycles` | cycles finished since the learner started |
| `pid` | the learner's process id |
| `time` | seconds since the epoch of the last change |

`perception-config cell-sim --lockstep` reads it to hold the simulated cell's next estimate while a
cycle runs (a real cell's robot takes seconds per pick, the simulated one none). A missing,
partial or foreign file reads as None: the file informs, it never stops a cell.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from ..util.atomic_file import atomic_write
from ..util.confine import confined

STATE_FILE = "learner_state.json"
STATES = ("idle", "training")


def write_state(learn_dir: str | os.PathLike, state: str, stored: int, every: int, cycles: int) -> None:
    """Rewrite the state file (atomically; an unwritable file or a link out of learn_dir is skipped)."""
    if state not in STATES:
        raise ValueError(f"learner state must be one of {STATES}, got {state!r}")
    learn_dir = Path(learn_dir)
    record = {"state": state, "stored": int(stored), "every": int(every), "cycles": int(cycles), "pid": os.getpid(),
              "time": time.time()}
    try:
        atomic_write(confined(learn_dir / STATE_FILE, learn_dir, "learner state"), json.dumps(record) + "\n")
    except (OSError, ValueError):
        pass


def read_state(learn_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The state file's record, or None when there is none or it is not one."""
    try:
        record = json.loads((Path(learn_dir) / STATE_FILE).read_text()[:4096])
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("state") not in STATES:
        return None
    for key in ("stored", "every", "cycles"):
        if not isinstance(record.get(key), int) or isinstance(record.get(key), bool):
            return None
    return record


def _running(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ProcessLookupError, TypeError, ValueError):
        return False
    except PermissionError:
        return True
    return True


class LearnerPace:
    """Hold a simulated cell's next estimate while its learner trains (`cell-sim --lockstep`).

    Called with the estimates done so far before each estimate: it returns at once when the
    learner is idle and no cycle is due, waits while the state file says `training`, and when a
    cycle is due (`done >= stored + every`) but has not begun (the learner polls the store every
    0.25 s, the store's write may lag the answer) waits up to `start_wait` seconds for it to
    begin. A learner that is not running (no state file yet, or its process gone) holds nothing;
    one hold lasts at most `timeout` seconds. `alive` is called while waiting (it raises when
    the cell's nodes died). `holds` and `seconds` count the waits."""

    def __init__(self, learn_dir: str | os.PathLike, timeout: float = 1800.0, start_wait: float = 3.0,
                 poll: float = 0.1) -> None:
        self.learn_dir = Path(learn_dir)
        self.timeout, self.start_wait, self.poll = float(timeout), float(start_wait), float(poll)
        self.holds = 0
        self.seconds = 0.0
        self.timeouts = 0

    def __call__(self, done: int, alive: Any = None) -> None:
        t0 = time.monotonic()
        due_since = None
        while True:
            now = time.monotonic()
            if now - t0 > self.timeout:
                self.timeouts += 1
                break
            st = read_state(self.learn_dir)
            if st is None or not _running(st.get("pid")):
                break
            if st["state"] == "idle":
                if done < st["stored"] + st["every"]:
                    break
                due_since = now if due_since is None else due_since
                if now - due_since >= self.start_wait:
                    break
            if alive is not None:
                alive()
            time.sleep(self.poll)
        waited = time.monotonic() - t0
        if waited >= self.poll:
            self.holds += 1
            self.seconds += waited

    def record(self) -> dict[str, Any]:
        return {"holds": self.holds, "seconds": round(self.seconds, 1), "timeouts": self.timeouts}
