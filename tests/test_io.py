"""The one atomic-write helper: content kinds, permissions, and what a failure leaves behind."""

import errno
import os
import stat

import numpy as np
import pytest

from sysid_bench import _io
from sysid_bench._io import atomic_write


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


def test_bytes_text_and_callable(tmp_path):
    atomic_write(tmp_path / "a.bin", b"\x00\x01")
    atomic_write(tmp_path / "b.txt", "héllo")
    # a callable gets a temporary path that ends in the target's suffix (numpy.savez keeps it)
    seen = []

    def write(p):
        seen.append(p)
        np.savez(p, x=np.arange(3))

    out = atomic_write(tmp_path / "sub" / "c.npz", write)
    assert out == tmp_path / "sub" / "c.npz"
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "b.txt").read_text(encoding="utf-8") == "héllo"
    assert seen[0].suffix == ".npz" and seen[0].parent == tmp_path / "sub"
    assert np.load(out)["x"].tolist() == [0, 1, 2]
    assert _leftovers(tmp_path) == [] and _leftovers(tmp_path / "sub") == []
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o644


def test_mode_is_applied(tmp_path):
    p = atomic_write(tmp_path / "x", "1", mode=0o600)
    assert stat.S_IMODE(os.stat(p).st_mode) == 0o600


def test_failing_writer_leaves_old_file_and_no_temp(tmp_path):
    target = tmp_path / "t.json"
    target.write_text("old")

    def broken(p):
        p.write_text("half")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        atomic_write(target, broken)
    assert target.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_disk_full_is_named(tmp_path, monkeypatch):
    target = tmp_path / "t.csv"
    target.write_text("old")

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_io.os, "fsync", no_space)
    with pytest.raises(OSError) as info:
        atomic_write(target, "new contents")
    assert str(info.value) == f"disk full writing {target}"
    assert info.value.errno == errno.ENOSPC
    assert target.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_disk_full_inside_a_callable_is_named(tmp_path):
    def no_space(p):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=r"^disk full writing .*y\.png$"):
        atomic_write(tmp_path / "y.png", no_space)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_target_is_one_line_naming_it(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    target = blocker / "t.txt"  # its "folder" is a file
    with pytest.raises(OSError) as info:
        atomic_write(target, "x", parents=False)
    msg = str(info.value)
    assert msg.startswith(f"cannot write {target}: ") and "\n" not in msg
    assert info.value.errno == errno.ENOTDIR
    # a folder in the target's place: the rename fails, the temporary file goes
    (tmp_path / "d").mkdir()
    with pytest.raises(IsADirectoryError, match="cannot write .*d"):
        atomic_write(tmp_path / "d", "x")
    assert _leftovers(tmp_path) == []


def test_bad_content_names_the_argument(tmp_path):
    with pytest.raises(ValueError, match="content: expected bytes, str or a callable.*int"):
        atomic_write(tmp_path / "z", 3)
    assert list(tmp_path.iterdir()) == []
