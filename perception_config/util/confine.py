"""Paths confined to a folder: a symbolic link may not lead out of it.

Online learning keeps its whole state in one folder (`learn_dir`: policies/, pick_success/,
frames/, candidates/, episodes.sqlite, learner.log). A link inside it that leads elsewhere (a
version file linked to a policy outside, `policies/` itself a link to another folder) would make
the learner load files nobody promoted, or a promotion write, and the frame ring delete, outside
the folder. `confined(path, root)` resolves every link on `path` (a dangling last one too) and
refuses a path that ends outside `root` (itself resolved, so a `learn_dir` that is a link is
fine); links that stay inside `root` are allowed. The check is made before each read or write;
it does not guard against a link swapped in between the check and the use.
"""
from __future__ import annotations

import os
from pathlib import Path


class ConfinementError(ValueError):
    """A path that leads (through a symbolic link) out of the folder it must stay in."""


def confined(path: str | os.PathLike, root: str | os.PathLike, what: str = "file",
             error: type[Exception] = ConfinementError) -> Path:
    """`path` with its links resolved, when that lies inside `root` (or is `root`); else `error`
    naming `what`, the path, where it leads and the root."""
    path = Path(path)
    try:
        top = Path(root).resolve()
        real = path.resolve()
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop
        raise error(f"{what} {path} cannot be resolved inside {root} ({exc})") from None
    if real != top and top not in real.parents:
        raise error(f"{what} {path} leads to {real}, outside {top}: a symbolic link out of that folder is refused "
                    "(the learning state must stay in its folder; replace the link by the file or folder itself)")
    return real


__all__ = ["ConfinementError", "confined"]
