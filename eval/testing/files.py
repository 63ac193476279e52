"""Files written whole or not at all, and the one-line error of a write that failed."""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Callable
from pathlib import Path


def write_message(path: Path, exc: OSError, after_full: str) -> str:
    """What a failed write to ``path`` says: what failed, why, the free space there, and what to
    do; ``after_full`` is what happens when the command runs again after a full disk."""
    try:
        free = f"{shutil.disk_usage(Path(path).parent).free / 1e6:.1f} MB free there"
    except OSError:
        free = "free space unknown"
    full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
    fix = (f"the disk is full: free space, then run the command again ({after_full})" if full else
           "make the folder writable or choose another --out")
    return f"cannot write {path} ({exc.strerror or exc}; {free}); {fix}"


def atomic_write(path: Path, text: str, error: Callable[[Path, OSError], Exception]) -> None:
    """Replace ``path`` with ``text`` so a reader sees the old file or the new, never half: the
    text goes to ``<name>.tmp`` (fsync'ed), renamed over ``path``. A failed write (a full disk)
    removes the ``.tmp``, leaves ``path`` as it was and raises ``error(path, exc)``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise error(path, exc) from exc
