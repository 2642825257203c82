"""Issue 38: the real clips in docs/sample/real/ are described (source, licence, truths) and
scripts/get_real_clips.py fetches only the recorded bytes. No network: ``file://`` URLs."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scripts_loader import load_script

# licences that allow redistributing a file with attribution (docs/real-footage.md); the GPL
# with its licence text kept and the copy under the GPL (docs/sample/real/ATTRIBUTION.md)
REDISTRIBUTABLE = {"MIT", "BSD-2-Clause", "BSD-3-Clause", "Apache-2.0", "CC-BY-4.0", "CC0-1.0",
                   "GPL-3.0-only", "GPL-3.0-or-later"}


@pytest.fixture(scope="module")
def grc():
    return load_script("get_real_clips")


def test_every_clip_names_its_source_licence_and_truths(grc):
    clips = grc.load_clips()
    # a real clip of every system (session 27: the spring's cart and the colliding pucks)
    assert {"ball", "pendulum", "spring", "collision"} <= {m["system"] for m in clips.values()}
    for name, m in clips.items():
        src = m["source"]
        assert len(src["commit"]) == 40 and len(src["blob_sha1"]) == 40, name
        assert src["url"].endswith(f"/{src['commit']}/{src['path']}"), name
        lic = m["licence"]
        # redistributable only under a licence that allows it, and then with its notice
        assert lic["redistributable"] == (lic["spdx"] in REDISTRIBUTABLE), name
        assert not lic["redistributable"] or lic["notice"], name
        assert m["truths"] and all({"name", "value", "unit", "stated_by"} <= set(t)
                                   for t in m["truths"]), name
        start, end = m["window_s"]
        assert 0 <= start < end <= m["video"]["seconds"] + 0.1, name
        # a clip not shipped is not in the repository
        shipped = list(grc.CLIP_DIR.glob(name + ".*"))
        assert m["shipped"] or [p.suffix for p in shipped] == [".json"], name


def test_git_blob_hash_is_gits():
    grc = load_script("get_real_clips")
    assert grc.git_blob_sha1(b"") == "e69de29bb2d1d6434b8b29ae775ad8c2e48c5391"
    assert grc.git_blob_sha1(b"hello\n") == "ce013625030ba8dba906f756967f9e9ca394464a"


def _meta(data: bytes, url: str) -> dict:
    grc = load_script("get_real_clips")
    return {"name": "demo", "system": "ball", "window_s": [0.5, 1.0],
            "source": {"repository": "o/r", "path": "clip.MP4", "commit": "0" * 40,
                       "blob_sha1": grc.git_blob_sha1(data), "bytes": len(data), "url": url}}


def test_download_keeps_only_the_recorded_bytes(grc, tmp_path):
    src = tmp_path / "src.bin"
    src.write_bytes(b"not really a video\n")
    meta = _meta(src.read_bytes(), src.as_uri())
    out = grc.download(meta, tmp_path / "dest")
    assert out.name == "demo.mp4" and out.read_bytes() == src.read_bytes()
    src.write_bytes(b"changed upstream\n")
    with pytest.raises(ValueError, match="expected 19 bytes"):
        grc.download(meta, tmp_path / "dest2")
    assert not (tmp_path / "dest2").exists()


def test_trim_keeps_the_window(grc, tmp_path):
    from sysid_bench.core.footage import read_video, write_video

    frames = np.zeros((20, 32, 48, 3), np.uint8)
    for i in range(20):
        frames[i, :, i * 2:i * 2 + 4] = 255  # a bar moving right, 2 px a frame
    clip = write_video(tmp_path / "clip.mp4", frames, fps=10)
    meta = _meta(clip.read_bytes(), clip.as_uri())
    out = grc.trim(meta, clip, tmp_path)
    got = read_video(out, fps=10, progress=False)
    assert got.frames.shape[0] == 5  # t in [0.5, 1.0) at 10 fps: frames 5..9
    assert abs(int(np.argmax(got.frames[0].mean(axis=0))) - 11) <= 2  # the bar of frame 5


def test_cli_lists_and_refuses_unknown_names(grc, capsys):
    assert grc.main(["--print"]) == 0
    urls = capsys.readouterr().out.split()
    assert urls and all(u.startswith("https://raw.githubusercontent.com/") for u in urls)
    with pytest.raises(SystemExit):
        grc.main(["no_such_clip"])
    assert "names: expected" in capsys.readouterr().err


def test_clip_json_is_json(grc):
    for path in grc.CLIP_DIR.glob("*.json"):
        json.loads(path.read_text(encoding="utf-8"))
