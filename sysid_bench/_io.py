"""Atomic file writes: one helper for every file the suite writes.

A reader (another process, a resumed run, a crash) must never see half a file. So every file is
written to a temporary file in the target's own folder (same file system, so the rename is atomic),
flushed to disk, then renamed over the target. On any failure the temporary file is removed and
the old target, if there was one, is left as it was.

Errors name the path: a full disk is ``OSError("disk full writing <path>")`` (``errno`` ENOSPC);
a target that cannot be written (no permission, read-only file system, missing folder, a folder in
its place) is one line that names the path and the reason, with the original exception's type and
``errno``.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_write"]

# errors that mean "this path cannot be written", reported as one line naming the path
_UNWRITABLE = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT, errno.EISDIR, errno.ENOTDIR}


def atomic_write(
    path,
    content: bytes | str | Callable[[Path], object],
    *,
    mode: int = 0o644,
    encoding: str = "utf-8",
    parents: bool = True,
) -> Path:
    """Write ``content`` to ``path`` atomically (temporary file in the same folder, then rename).

    Parameters
    ----------
    path : str or os.PathLike
        The target file. Its folder is created when ``parents`` is true.
    content : bytes, str or callable
        Bytes are written as they are, text encoded with ``encoding``. A callable is given the
        temporary file's path (a ``pathlib.Path`` that ends in the target's suffix, so writers
        that choose a format by the suffix, such as ``numpy.savez`` or PyAV, keep working) and
        must write the whole file there; its return value is ignored.
    mode : int
        Permission bits of the written file (a temporary file is created private).
    encoding : str
        Encoding of text ``content``.
    parents : bool
        Create the target's missing parent folders.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        ``content`` is none of bytes, str or a callable.
    OSError
        The disk is full (``"disk full writing <path>"``, errno ENOSPC) or the target cannot be
        written (one line naming the path); the old target is then unchanged and no temporary
        file is left behind. Exceptions raised by a callable ``content`` propagate unchanged
        (after the temporary file is removed).
    """
    if isinstance(content, str):
        data = content.encode(encoding)
    elif isinstance(content, (bytes, bytearray, memoryview)):
        data = bytes(content)
    elif callable(content):
        data = None
    else:
        raise ValueError(
            f"content: expected bytes, str or a callable taking a path, got {type(content).__name__}"
        )
    path = Path(path)
    tmp = None
    try:
        if parents:
            path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(
            prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
        )
        tmp = Path(name)
        if data is not None:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
        else:
            os.close(fd)
            content(tmp)
            # the writer may have closed without syncing: sync what is on disk now
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
        tmp = None
    except OSError as e:
        raise _named(e, path) from None
    finally:
        if tmp is not None:
            try:
                tmp.unlink()
            except OSError:
                pass
    _sync_dir(path.parent)
    return path


def _named(e: OSError, path: Path) -> OSError:
    """``e`` as a one-line error that names ``path`` (ENOSPC and unwritable targets)."""
    if e.errno == errno.ENOSPC:
        err = OSError(f"disk full writing {path}")
    elif e.errno in _UNWRITABLE:
        err = type(e)(f"cannot write {path}: {e.strerror or e}")
    else:
        return e
    err.errno = e.errno  # (no .filename: it would turn str(err) back into the long form)
    return err


def _sync_dir(folder: Path) -> None:
    """Make the rename itself durable where the platform allows (best effort)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
