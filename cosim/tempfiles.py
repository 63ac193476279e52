"""Private folders under the temp folder for what cosim writes there (issue 57 item 14).

The temp folder (``/tmp``) is shared by every user of the machine, so a fixed name there is
one another user can take first, as a folder of theirs or a link to one of your files. A
folder made by :func:`private_folder` is this user's alone (mode 0700, checked, never a link);
what goes in it (the meshes of an environment's cameras, ``cosim/mirror.py``; the CLI's error
logs, ``eval/cli/__init__.py``) is created there with exclusive, non-following opens.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

__all__ = ["private_folder"]


def private_folder(name: str) -> Path:
    """``<temp>/<name>``, created with mode 0700 (or reused where it is already a folder of this
    user's that no one else can write, not a link); a random ``<temp>/<name>-XXXX`` instead
    where the name is taken by anything else."""
    folder = Path(tempfile.gettempdir()) / name
    try:
        folder.mkdir(mode=0o700)
        return folder
    except FileExistsError:
        pass
    info = os.lstat(folder)  # lstat: a link is not followed, and is not ours to use
    if stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() and not info.st_mode & 0o077:
        return folder
    return Path(tempfile.mkdtemp(prefix=f"{name}-"))
