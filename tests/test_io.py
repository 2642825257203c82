"""The one atomic-write helper: content kinds, permissions, and what a failure leaves behind."""

import errno
import os
import stat

import numpy as np
import pytest

from sysid_bench.core import _io
from sysid_bench.core._io import atomic_write


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


def _write_three(tag):
    def write(d):
        for name in ("estimates.csv", "estimates.json", "track.png"):
            (d / name).write_text(f"{tag} {name}")
    return write


def test_atomic_folder_new_and_replaced_whole(tmp_path):
    out = tmp_path / "sub" / "out"
    assert _io.atomic_folder(out, _write_three("v1")) == out
    assert (out / "track.png").read_text() == "v1 track.png"
    (out / "notes.txt").write_text("mine")
    (out / "keep").mkdir()
    (out / "keep" / "a.txt").write_text("a")
    _io.atomic_folder(out, _write_three("v2"), keep_others=True)
    assert {p.read_text() for p in out.glob("estimates.*")} == {"v2 estimates.csv",
                                                                 "v2 estimates.json"}
    # files it did not write are kept; nothing temporary is left beside the folder
    assert (out / "notes.txt").read_text() == "mine" and (out / "keep" / "a.txt").read_text() == "a"
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]
    _io.atomic_folder(out, _write_three("v3"))  # keep_others=False: exactly what was written
    assert sorted(p.name for p in out.iterdir()) == ["estimates.csv", "estimates.json", "track.png"]


def test_atomic_folder_failing_writer_leaves_the_old_folder_unmixed(tmp_path):
    out = tmp_path / "out"
    _io.atomic_folder(out, _write_three("v1"))

    def half(d):  # the old code wrote file by file into ``out``: a failure left a mix
        (d / "estimates.csv").write_text("v2 estimates.csv")
        raise RuntimeError("plot failed")

    with pytest.raises(RuntimeError, match="plot failed"):
        _io.atomic_folder(out, half, keep_others=True)
    assert {p.read_text() for p in out.iterdir()} == {f"v1 {n}" for n in
                                                     ("estimates.csv", "estimates.json", "track.png")}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_folder_swap_failure_puts_the_old_folder_back(tmp_path, monkeypatch):
    out = tmp_path / "out"
    _io.atomic_folder(out, _write_three("v1"))
    real = os.replace
    calls = []

    def flaky(a, b):
        calls.append((a, b))
        if len(calls) == 2:  # the rename of the new folder into place
            raise OSError(errno.EACCES, "Permission denied")
        return real(a, b)

    monkeypatch.setattr(_io.os, "replace", flaky)
    with pytest.raises(PermissionError, match=f"cannot write {out}"):
        _io.atomic_folder(out, _write_three("v2"))
    monkeypatch.undo()
    assert (out / "track.png").read_text() == "v1 track.png"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_folder_refuses_a_file_target(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(ValueError, match="path: expected a folder"):
        _io.atomic_folder(f, _write_three("v1"))
    assert f.read_text() == "x"
