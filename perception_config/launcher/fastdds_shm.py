"""Remove the shared-memory segments that dead Fast DDS participants left in /dev/shm.

Every participant creates a segment `fastdds_<16 hex>` (8 MB with the shipped profile, 512 KB
with Fast DDS's default) and a lock file `fastdds_<16 hex>_el` that it holds (flock) for its
whole life. A clean stop removes both; a SIGKILLed process leaves them, and nothing reclaims
them: /dev/shm is memory. A segment whose lock file nobody holds is stale - the rule of Fast
DDS's own `fastdds shm clean` (tools/fastdds/shm/clean.py in the wheels), done here without
spawning it (that script runs whatever `python3` is first on the PATH).

Only segments are removed. Port files (`fastdds_port<N>`, `sem.fastdds_port<N>_mutex`) are
named after the UDP-like port number, so they are reused by the next participant on that port
rather than accumulating, and Fast DDS repairs a port whose listener died when it opens it;
removing one while another process opens it would break that process's discovery.

Called once at the start of every node (node_main.run_nodes, bag_replay_node.main), before
rclpy.init. Cost: one directory listing and one open+flock per lock file (0.1-0.3 ms for
184 files here). A lock file younger than `min_age_s` is left alone: its owner may be
between creating it and locking it.
"""
from __future__ import annotations

import fcntl
import os
import re
import time
from pathlib import Path

SHM_DIR = Path("/dev/shm")
MIN_AGE_S = 2.0
MAX_ENTRIES = 100_000  # bound the work on a /dev/shm full of other files
_SEGMENT_LOCK = re.compile(r"fastdds_[0-9a-f]{16}_el")


def _is_held(lock_path: Path) -> bool:
    """Whether some process holds a flock on `lock_path` (True also when it cannot be opened)."""
    try:
        fd = os.open(lock_path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return False
    except OSError:
        return True  # not ours to judge (permissions, a special file)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # also releases the lock we may have taken
    return False


def clean_stale_fastdds_shm(shm_dir: Path = SHM_DIR, min_age_s: float = MIN_AGE_S) -> list[str]:
    """Remove every Fast DDS segment in `shm_dir` whose lock file is older than `min_age_s`
    seconds and held by no process; return the names of the files removed (segment and lock).
    Files that vanish meanwhile or cannot be removed are skipped: never raises for them."""
    removed: list[str] = []
    try:
        with os.scandir(shm_dir) as entries:
            names = [entry.name for _, entry in zip(range(MAX_ENTRIES), entries)]
    except OSError:
        return removed  # no /dev/shm: Fast DDS falls back to UDP and leaves nothing
    now = time.time()
    for name in names:
        if not _SEGMENT_LOCK.fullmatch(name):
            continue
        lock = shm_dir / name
        try:
            if now - lock.lstat().st_mtime < min_age_s:
                continue
        except OSError:
            continue
        if _is_held(lock):
            continue
        for path in (shm_dir / name[:-3], lock):  # the segment first, so a lock never outlives it unseen
            try:
                path.unlink()
                removed.append(path.name)
            except FileNotFoundError:
                pass
            except OSError:
                break
    return removed
