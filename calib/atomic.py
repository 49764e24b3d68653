"""Atomic file writes: a temp file in the target folder, fsync, then rename; never half-written."""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


@contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """A binary file to write ``path`` through: it appears under its name, whole, only when the
    ``with`` block ends without an exception (temp file in the same folder, fsync, rename);
    otherwise the temp file is removed and any old ``path`` is left as it was."""
    path = Path(path)
    if path.is_dir():  # else the rename fails at the end, naming the temp file
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp makes the file private (0600); a result is meant to be read by others: keep
        # the mode of the file being replaced, else the usual 0644.
        try:
            mode = path.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o644
        os.chmod(tmp, mode)
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` so that readers see either the old file or the whole new one."""
    with atomic_output(path) as f:
        f.write(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Text version of :func:`write_bytes_atomic` (UTF-8)."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def os_error_line(e: OSError) -> str:
    """One line for a command's error output: the file and why (``IsADirectoryError`` on an
    output path, ``PermissionError`` on an input, ...), without the traceback."""
    why = e.strerror or str(e)
    name = e.filename2 if e.filename2 is not None else e.filename  # a rename's: its target
    return f"{name}: {why}" if name is not None else why
