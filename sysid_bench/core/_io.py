"""Atomic file writes: one helper for every file the suite writes.

A reader (another process, a resumed run, a crash) must never see half a file. So every file is
written to a temporary file in the target's own folder (same file system, so the rename is atomic),
flushed to disk, then renamed over the target. On any failure the temporary file is removed and
the old target, if there was one, is left as it was.

A folder of files that belong together (a dataset, ``identify --out``'s three outputs) is built
the same way by :func:`atomic_folder`: in a temporary folder beside the target, then renamed
into place whole, so a reader sees the old folder or the new one, never a mix.

Errors name the path: a full disk is ``OSError("disk full writing <path>")`` (``errno`` ENOSPC);
a target that cannot be written (no permission, read-only file system, missing folder, a folder in
its place) is one line that names the path and the reason, with the original exception's type and
``errno``.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_write", "atomic_folder", "replace_folder"]

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


def atomic_folder(path, write: Callable[[Path], object], *, keep_others: bool = False,
                  parents: bool = True) -> Path:
    """Build the folder ``path`` as a whole: ``write`` fills a temporary folder beside it, which
    then takes ``path``'s place by rename.

    A new ``path`` is the temporary folder renamed (atomic). An existing one is moved aside
    (``.<name>.old.<random>`` beside it), the new folder renamed in, and the old one removed, so
    a reader never sees new and old files mixed (writing file by file into the old folder
    could leave a new ``estimates.csv`` beside an old ``track.png``); if the swap fails the old
    folder is put back. Between the two renames ``path`` is briefly absent; a crash exactly
    there leaves the previous folder beside it under the ``.old`` name.

    Parameters
    ----------
    path : str or os.PathLike
        The target folder.
    write : callable
        Given the temporary folder (``pathlib.Path``, empty, on the target's file system), writes
        every file there; its return value is ignored.
    keep_others : bool
        Entries of an existing ``path`` that ``write`` did not write are carried into the new
        folder (hard links where the file system allows, else copies): the folder keeps files
        it did not write. False: the new folder is exactly what ``write`` wrote.
    parents : bool
        Create ``path``'s missing parent folders.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        ``path`` exists and is not a folder.
    OSError
        ``path``'s folder cannot be written (one line naming the path); ``path`` is unchanged and
        no temporary folder is left. Exceptions raised by ``write`` propagate unchanged (after the
        temporary folder is removed).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"path: expected a folder, got the file {path}")
    tmp = None
    try:
        if parents:
            path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
        write(tmp)
        if keep_others and path.exists():
            _carry_over(path, tmp)
        _swap_in(tmp, path)
        tmp = None
    except OSError as e:
        raise _named(e, path) from None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    _sync_dir(path.parent)
    return path


def replace_folder(src, path) -> Path:
    """Move the finished folder ``src`` to ``path`` (same file system), replacing a folder there
    as :func:`atomic_folder` does (moved aside, ``src`` renamed in, the old one removed; put back
    if the rename fails). For writers that build ``src`` themselves (a resumable dataset)."""
    src, path = Path(src), Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"path: expected a folder, got the file {path}")
    try:
        _swap_in(src, path)
    except OSError as e:
        raise _named(e, path) from None
    _sync_dir(path.parent)
    return path


def _swap_in(tmp: Path, path: Path) -> None:
    """``tmp`` renamed to ``path``; an existing ``path`` is moved aside first, then removed."""
    if not path.exists():
        os.replace(tmp, path)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=path.parent))
    os.replace(path, old)  # onto an empty folder: allowed by rename(2)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.replace(old, path)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _carry_over(old: Path, new: Path) -> None:
    """Entries of folder ``old`` missing from ``new``, linked (or copied) into ``new``."""
    for entry in old.iterdir():
        dest = new / entry.name
        if dest.exists() or dest.is_symlink():
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.copytree(entry, dest, symlinks=True, copy_function=_link_or_copy)
        else:
            _link_or_copy(entry, dest)


def _link_or_copy(src, dst) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)
