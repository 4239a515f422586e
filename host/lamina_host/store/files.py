"""Writing patient-derived files: owner-only, never through a link, never over another file.

Folders Lamina creates are 0700 and files 0600. A file the user named by its folder
(a scan's outputs) is written to a temporary file in the same folder and renamed over
the name (:func:`replace_file`): a symbolic link planted there is replaced, its target
never touched. A file the user named to be new (an export) is created exclusively
without following links (:func:`write_new_file`), so an existing file or link is
refused rather than overwritten.
"""

from __future__ import annotations

import errno
import json
import math
import os
import sqlite3
import stat
import tempfile
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import Any

from lamina_shared.errors import LaminaError

PRIVATE_FILE = 0o600
PRIVATE_FOLDER = 0o700


class OutputError(LaminaError, RuntimeError):
    """An output cannot be written where asked; the text names the path and what to do.

    ``errno`` is the file system's reason when there is one (``errno.ENOSPC``: the disk
    is full), so a caller can say how to go on.
    """

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno


def disk_full(exc: BaseException) -> bool:
    """Return True if ``exc`` says a disk is full (a file's or the scan library's).

    Args:
        exc: an OSError, an :class:`OutputError` or a ``sqlite3.Error``.

    Returns:
        True for ENOSPC and EDQUOT, and SQLite's "database or disk is full".
    """
    if isinstance(exc, OutputError | OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        return code == sqlite3.SQLITE_FULL or "disk is full" in str(exc)
    return False


def _cannot_write(path: Path, exc: OSError) -> OutputError:
    return OutputError(f"cannot write {path} ({_reason(exc)})", exc.errno)


def finite_json(value: Any) -> Any:
    """Return ``value`` with every non-finite number (NaN, infinity) replaced by None.

    Args:
        value: JSON-able data (dicts, lists, tuples, numbers, strings).

    Returns:
        The same data, fit for strict JSON parsers (``NaN`` is not JSON: null is).
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(item) for item in value]
    return value


def json_text(value: Any) -> str:
    """Return ``value`` as indented strict JSON text (non-finite numbers as null), newline ended."""
    return json.dumps(finite_json(value), indent=2, allow_nan=False) + "\n"


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def prepare_output_folder(folder: Path, allow_files: bool = False) -> Path:
    """Create ``folder`` (0700) or check an existing one; prove it is writable.

    Args:
        folder: the output folder the user named.
        allow_files: an existing folder may hold files (resuming into a scan's own folder).

    Raises:
        OutputError: it is a file, lies under a file, is not empty, or cannot be written.
    """
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"output folder {folder} is a file: name a new folder")
    if folder.is_dir() and not allow_files and any(folder.iterdir()):
        raise OutputError(
            f"output folder {folder} is not empty; choose a new folder so "
            "no earlier scan is overwritten"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=PRIVATE_FOLDER)
        if folder.stat().st_uid == os.getuid():
            folder.chmod(PRIVATE_FOLDER)
        fd, probe = tempfile.mkstemp(prefix=".lamina-probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(
            f"cannot write into output folder {folder} ({_reason(exc)}): "
            "name a folder you can write"
        ) from None
    return folder


def replace_file(path: Path, write: Callable[[Path], object]) -> Path:
    """Have ``write`` fill a private temporary file beside ``path``, then rename it to ``path``.

    The rename replaces whatever entry ``path`` is (a planted link included) and never
    writes through it.

    Raises:
        OutputError: the folder cannot be written or ``path`` is a folder.
    """
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    os.close(fd)
    temporary = Path(name)
    try:
        write(temporary)
        os.chmod(temporary, PRIVATE_FILE)
        os.replace(temporary, path)
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    finally:
        with suppress(FileNotFoundError):
            temporary.unlink()
    return path


def _exists(path: Path) -> str:
    return f"{path} already exists: choose a new file name"


def new_file_problem(path: Path) -> str | None:
    """Return why ``path`` cannot be a new file (it exists, or lies in no folder), or None.

    A link counts as existing, a dangling one too: nothing is written through it.
    """
    if path.exists() or path.is_symlink():
        return _exists(path)
    if not path.parent.is_dir():
        return f"folder {path.parent} does not exist: create it first or name a file in another"
    return None


def write_new_file(path: Path, data: bytes) -> Path:
    """Create ``path`` (0600) holding ``data``; refuse an existing file or link, never follow one.

    Raises:
        OutputError: the file exists, its folder does not, or it cannot be written.
    """
    if problem := new_file_problem(path):
        raise OutputError(problem)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, PRIVATE_FILE)
    except FileExistsError:  # created since the check: the flags refuse it all the same
        raise OutputError(_exists(path)) from None
    except OSError as exc:
        raise _cannot_write(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
    except OSError as exc:
        with suppress(OSError):
            path.unlink()
        raise _cannot_write(path, exc) from None
    return path


def tighten(path: Path) -> bool:
    """Make an existing file owner-only; return True if it was readable by others before."""
    try:
        mode = stat.S_IMODE(os.lstat(path).st_mode)
    except FileNotFoundError:
        return False
    if not mode & 0o077 or stat.S_ISLNK(os.lstat(path).st_mode):
        return False
    os.chmod(path, PRIVATE_FILE)
    return True
