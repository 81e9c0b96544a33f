"""Whole-or-absent file writes: a reader (or a crash, or a full disk) never sees half a file, and
the old file stays until the new one is complete and on disk."""
from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import IO, Callable

FILE_MODE = 0o644           # readable by a player running as another user, as `open` would make it


class WriteError(OSError):
    """A file could not be written; the message names it and the free space on its disk."""


def write_failure(path: str | Path, error: OSError) -> WriteError:
    """``error`` restated with the file and the free space on its disk."""
    if isinstance(error, WriteError):
        return error
    path = Path(path)
    try:
        free = f'{shutil.disk_usage(path.parent).free / 1e6:.1f} MB free'
    except OSError:
        free = 'free space unknown'
    what = 'disk full' if error.errno == errno.ENOSPC else (error.strerror or str(error))
    return WriteError(error.errno, f'could not write {path}: {what} ({free} on its disk)')


def atomic_write(path: str | Path, write: Callable[[IO], None], binary: bool = True) -> Path:
    """Call ``write(f)`` on a temporary file beside ``path``; flush, fsync and rename it over
    ``path``. A failure (a full disk included) removes the temporary file and raises an OSError
    naming ``path`` and the free space."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f'.{target.name}.', suffix='.tmp')
    try:
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, 'wb' if binary else 'w') as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        publish(tmp, target)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise write_failure(target, e) from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def publish(tmp: str | Path, target: Path) -> None:
    """Rename a finished temporary file over ``target`` and make the rename itself durable."""
    os.replace(tmp, target)
    dir_fd = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def append_line(path: str | Path, line: str) -> None:
    """Append one line and fsync; on failure the file is cut back to its previous length, so it
    never ends in half a line."""
    target = Path(path)
    data = line.encode() + b'\n'
    fd = os.open(target, os.O_WRONLY | os.O_APPEND | os.O_CREAT, FILE_MODE)
    try:
        size = os.fstat(fd).st_size
        try:
            if os.write(fd, data) != len(data):
                raise OSError(errno.ENOSPC, 'short write')
            os.fsync(fd)
        except OSError as e:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass
            raise write_failure(target, e) from e
    finally:
        os.close(fd)


def write_json(path: str | Path, doc) -> Path:
    """``doc`` as indented JSON, written atomically."""
    text = json.dumps(doc, indent=2)
    return atomic_write(path, lambda f: f.write(text), binary=False)
