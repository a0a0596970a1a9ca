"""Every file the pipeline writes into a folder a user or a team may share (``paths.results``,
``--out``, the stage cache, the MLflow store's helpers) is written by :func:`replace_file`
(issue 51 item 1): created under a name nobody can guess (``tempfile.mkstemp`` in the target
folder: ``O_CREAT|O_EXCL|O_NOFOLLOW``, so a link planted there is never followed), filled from an
open descriptor, renamed over the target (``os.replace``: atomic, and a link at the target is
replaced, not followed), then checked to be the very file written.  Imports nothing from the
pipeline."""
from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path
from typing import Callable

__all__ = ["replace_file", "UnsafeWrite", "read_nofollow", "umask"]


class UnsafeWrite(OSError):
    """The file renamed into place is not the one written (someone swapped it between the two)."""


def umask() -> int:
    """This process's umask (read from /proc on Linux; else set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def replace_file(path: Path, data: bytes | str, before: Callable[[bytes], None] | None = None) -> Path:
    """Write ``data`` as ``path`` whole: a new file of a random name in its folder (never an existing
    file, never through a link), mode ``0666 & ~umask`` as ``open`` would give, renamed over ``path``;
    ``before(data)`` runs between the two (e.g. listing the new file's hash as the pipeline's).
    Raises :class:`UnsafeWrite` if what is at ``path`` after the rename is not that file."""
    path = Path(path)
    blob = data.encode() if isinstance(data, str) else bytes(data)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
            f.flush()
            os.fchmod(f.fileno(), 0o666 & ~umask())
            mine = os.fstat(f.fileno())
        if before is not None:
            before(blob)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    now = os.lstat(path)
    if (now.st_dev, now.st_ino) != (mine.st_dev, mine.st_ino) or not stat.S_ISREG(now.st_mode):
        raise UnsafeWrite(f"{path} is not the file just written (it was replaced during the rename): someone else "
                          "writes into this folder; write outputs to a folder only you can write to")
    return path


def read_nofollow(path: Path) -> bytes:
    """The bytes of the regular file ``path``, read from one descriptor opened without following a
    link (``OSError`` for a link, a folder, a device or a fifo)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise OSError(f"{path} is not a regular file")
        return f.read()
