"""Versioned files of online learning: every promotion is kept, any version can serve again.

Policies (`<learn_dir>/policies/`) and the pick-success score (`<learn_dir>/pick_success/`) are
versioned the same way; `what` names which in the messages.

A folder (`<learn_dir>/policies/`) holds `v0000.<ext>` (version 0: what served first), `v0001...`
(one per promoted candidate) and `versions.json`:
    {"versions": [{"version": "v0001", "file": "v0001.safetensors", "created": unix s,
                   "info": {...what the learner measured...}}, ...],
     "selected": null | "v0002"}
`selected` pins a version (a rollback); null serves the newest. Files are never deleted or
rewritten: a promotion writes a new file, then the index, both atomically (atomic_file), under an
exclusive lock (`.lock`, fcntl) because the configurator (select) and the learner process
(promote) both change the index. A reader sees the old index or the new one, never a mix.

Everything stays inside `root` (the learn directory; default: the folder's parent): the folder,
the index, the lock and every version file are checked before each read or write
(util/confine.py), so a link that leads out of it (`policies/` linked to another folder, a
version file or versions.json linked to a file elsewhere) is a PolicyVersionError naming the
path and where it leads; a folder that leads out is refused when the object is built, before
anything is created. Links that stay inside `root` are allowed.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import re
import time
from pathlib import Path
from typing import Any, Iterator

from .atomic_file import atomic_write
from .confine import confined
from .safe_json import read_json_file

INDEX = "versions.json"
VERSION_RE = re.compile(r"^v\d{4,}$")


class PolicyVersionError(ValueError):
    """An unknown version, or a versions.json that cannot be read; the message names the folder."""


class PolicyVersions:
    """The versions in `folder` (created when absent), confined to `root` (default: the folder's
    parent, the learn directory)."""

    def __init__(self, folder: str | Path, what: str = "policy", root: str | Path | None = None) -> None:
        self.folder = Path(folder)
        self.what = what
        self.root = Path(root) if root is not None else self.folder.parent
        self._inside(self.folder, "versions folder")  # before mkdir: nothing is created outside
        self.folder.mkdir(parents=True, exist_ok=True)
        self.index = self.folder / INDEX

    def _inside(self, path: Path, what: str) -> Path:
        """`path` resolved; PolicyVersionError when it (or the folder) leads out of the root."""
        return confined(path, self.root, f"{self.what} {what}", PolicyVersionError)

    def _checked(self, path: Path, what: str) -> Path:
        self._inside(self.folder, "versions folder")
        return self._inside(path, what)

    # -- reading -------------------------------------------------------------------------------
    def _read(self) -> dict[str, Any]:
        index = self._checked(self.index, "versions index")
        if not index.exists():
            return {"versions": [], "selected": None}
        try:
            data = read_json_file(index)
        except (OSError, ValueError) as exc:
            raise PolicyVersionError(f"{self.what} versions {self.index} cannot be read ({exc}): the {self.what} "
                                     "files are kept; restore the index or move the folder aside") from None
        if not (isinstance(data, dict) and isinstance(data.get("versions"), list)
                and all(isinstance(v, dict) and VERSION_RE.match(str(v.get("version", ""))) and v.get("file")
                        for v in data["versions"])):
            raise PolicyVersionError(f"{self.what} versions {self.index} is not a versions index")
        return data

    def list(self) -> list[dict[str, Any]]:
        """Every kept version, oldest first: {"version", "file", "created", "info"}."""
        return list(self._read()["versions"])

    def newest(self) -> str | None:
        versions = self.list()
        return versions[-1]["version"] if versions else None

    def selected(self) -> str | None:
        """The pinned version (a rollback), or None: the newest serves."""
        return self._read().get("selected") or None

    def current(self) -> str | None:
        """The version that should serve: the pinned one, else the newest; None when there is none."""
        data = self._read()
        if data.get("selected"):
            return str(data["selected"])
        return data["versions"][-1]["version"] if data["versions"] else None

    def path(self, version: str) -> Path:
        """The file of `version`; PolicyVersionError naming the kept ones when unknown."""
        for v in self.list():
            if v["version"] == version:
                path = self.folder / Path(v["file"]).name
                self._checked(path, f"version {version} file")
                return path
        raise PolicyVersionError(f"unknown {self.what} version {version!r} in {self.folder} "
                                 f"(kept: {', '.join(v['version'] for v in self.list()) or 'none'})")

    def stamp(self) -> tuple[int, int] | None:
        """(mtime_ns, size) of the index: a cheap test whether anything changed."""
        try:
            st = self.index.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    # -- writing -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        with open(self._checked(self.folder / ".lock", "versions lock"), "a+") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def _write(self, data: dict[str, Any]) -> None:
        atomic_write(self._checked(self.index, "versions index"), json.dumps(data, indent=1) + "\n")

    def promote(self, src_path: str | Path, info: dict[str, Any] | None = None) -> str:
        """Keep a copy of the file `src_path` as the next version; its name ("v0003").
        The pin (if any) stays: a rolled-back configurator keeps its version until unpinned."""
        src = Path(src_path)
        payload = src.read_bytes()
        with self._locked():
            data = self._read()
            number = max((int(v["version"][1:]) for v in data["versions"]), default=-1) + 1
            version = f"v{number:04d}"
            name = version + (src.suffix or ".safetensors")
            atomic_write(self._checked(self.folder / name, f"version {version} file"), payload)
            data["versions"].append({"version": version, "file": name, "created": time.time(),
                                     "info": json.loads(json.dumps(info or {}))})
            self._write(data)
        return version

    def select(self, version: str | None) -> None:
        """Pin `version` (a rollback or roll-forward); "" or None unpins (the newest serves)."""
        with self._locked():
            data = self._read()
            if version:
                known = [v["version"] for v in data["versions"]]
                if version not in known:
                    raise PolicyVersionError(f"unknown {self.what} version {version!r} in {self.folder} "
                                             f"(kept: {', '.join(known) or 'none'})")
            data["selected"] = version or None
            self._write(data)
