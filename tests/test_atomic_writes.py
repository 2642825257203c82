"""One helper writes files atomically (``sysid_bench.core._io.atomic_write``): no module of the
package, the methods or the scripts renames a temporary file of its own; folders moved into place
whole (a dataset, an identify run's outputs) go through ``atomic_folder``/``replace_folder``
(issue 37: three hand-written copies wrote file by file into an existing folder)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: a rename or a temporary file made by hand
HAND_WRITTEN = re.compile(r"\bos\.(replace|rename)\(|\bmkstemp\(|\bmkdtemp\(|NamedTemporaryFile\(|"
                          r"\bshutil\.move\(")
#: where it is allowed, and why
ALLOWED = {
    "sysid_bench/core/_io.py": "the helpers themselves",
}


def _hand_written(files) -> list[str]:
    return [f"{f.relative_to(ROOT)}:{i}: {ln.strip()}"
            for f in files for i, ln in enumerate(f.read_text().splitlines(), 1)
            if HAND_WRITTEN.search(ln) and not ln.lstrip().startswith("#")
            and str(f.relative_to(ROOT)) not in ALLOWED]


def test_no_hand_written_temp_file_and_rename():
    files = [p for d in ("sysid_bench", "methods", "scripts") for p in (ROOT / d).rglob("*.py")
             if "__pycache__" not in p.parts]
    found = _hand_written(files)
    assert not found, ("write through sysid_bench.core._io.atomic_write instead:\n" + "\n".join(found))
    assert all((ROOT / f).is_file() for f in ALLOWED)  # a stale entry would hide nothing


def test_the_scan_sees_a_hand_written_rename(tmp_path, monkeypatch):
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    f = tmp_path / "w.py"
    f.write_text("import os\nfd, t = tempfile.mkstemp()\nos.replace(t, 'x')\n# os.replace(a, b)\n"
                 "d = tempfile.mkdtemp()\n")
    assert [h.split(":")[1] for h in _hand_written([f])] == ["2", "3", "5"]
