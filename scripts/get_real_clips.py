"""Download the real camera clips listed in ``docs/sample/real/`` from where their authors publish them.

Each ``docs/sample/real/<name>.json`` names a clip in a public GitHub repository (repository,
path, commit, the file's git blob hash and size), its licence, the truths its authors state and
the window of the clip that matters. None of the clips is in this repository (see
``docs/real-footage.md`` for why); this script fetches them when *you* run it::

    python scripts/get_real_clips.py --list                 # what there is; nothing fetched
    python scripts/get_real_clips.py --print                # the download URLs; nothing fetched
    python scripts/get_real_clips.py                        # all clips into runs/real_clips/
    python scripts/get_real_clips.py pendulum_necrosskull --trim --dest runs/real_clips

A downloaded file must have the size and git blob hash the JSON records (the bytes at that
commit), else it is discarded and the script exits 1. ``--trim`` also writes
``<name>_trim.mp4``: the JSON's ``window_s`` re-encoded as H.264 at the file's frame rate (a
small file of the part that matters; ``sysid-bench identify --start S --end E`` reads the same
window from the whole file). Files are written atomically. Clips whose licence does
not allow redistribution (``licence.redistributable`` false) are for your own use: do not commit
them anywhere.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLIP_DIR = ROOT / "docs" / "sample" / "real"
DEFAULT_DEST = ROOT / "runs" / "real_clips"
REQUIRED = ("name", "system", "source", "licence", "video", "truths", "window_s")
SOURCE_KEYS = ("repository", "path", "commit", "blob_sha1", "bytes", "url")


def load_clips(clip_dir=CLIP_DIR) -> dict[str, dict]:
    """Read every clip description in ``clip_dir``.

    Parameters
    ----------
    clip_dir : str or Path
        Folder of ``<name>.json`` files.

    Returns
    -------
    dict
        Name -> the JSON object, sorted by name.

    Raises
    ------
    ValueError
        A file misses a required key, or its ``name`` is not its file name.
    """
    clips = {}
    for path in sorted(Path(clip_dir).glob("*.json")):
        meta = json.loads(path.read_text(encoding="utf-8"))
        missing = [k for k in REQUIRED if k not in meta]
        missing += [f"source.{k}" for k in SOURCE_KEYS if k not in meta.get("source", {})]
        if missing:
            raise ValueError(f"{path.name}: expected keys {', '.join(missing)}, got none")
        if meta["name"] != path.stem:
            raise ValueError(f"{path.name}: expected name {path.stem!r}, got {meta['name']!r}")
        clips[meta["name"]] = meta
    return clips


def git_blob_sha1(data: bytes) -> str:
    """The hash git gives a file's bytes (``git hash-object``): sha1 of ``blob <size>\\0<data>``."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def check_bytes(meta: dict, data: bytes) -> None:
    """Raise ``ValueError`` unless ``data`` is the file the clip's JSON records."""
    src = meta["source"]
    if len(data) != src["bytes"]:
        raise ValueError(f"{meta['name']}: expected {src['bytes']} bytes from {src['url']}, "
                         f"got {len(data)}")
    got = git_blob_sha1(data)
    if got != src["blob_sha1"]:
        raise ValueError(f"{meta['name']}: expected git blob {src['blob_sha1']}, got {got}")


def download(meta: dict, dest, *, url: str | None = None, timeout: float = 60.0) -> Path:
    """Fetch one clip, check it, and write it to ``dest/<name><suffix>`` atomically.

    Parameters
    ----------
    meta : dict
        One clip's JSON object.
    dest : str or Path
        Output folder (created).
    url : str, optional
        Fetch from here instead of ``meta["source"]["url"]`` (a mirror, or a ``file://`` URL).
    timeout : float
        Seconds to wait for the server.

    Returns
    -------
    Path
        The written file.
    """
    from sysid_bench.core._io import atomic_write

    src = meta["source"]
    with urllib.request.urlopen(url or src["url"], timeout=timeout) as resp:
        data = resp.read()
    check_bytes(meta, data)
    out = Path(dest) / (meta["name"] + Path(src["path"]).suffix.lower())
    return atomic_write(out, data)


def trim(meta: dict, path, dest) -> Path:
    """Re-encode the JSON's ``window_s`` of the clip at ``path`` as ``dest/<name>_trim.mp4``.

    Frames whose presentation time lies in ``[start, end)`` are kept, in colour, at the
    stream's average frame rate (H.264, crf 18).

    Returns
    -------
    Path
        The written file.
    """
    import av
    import numpy as np

    from sysid_bench.core.footage import write_video

    start, end = (float(v) for v in meta["window_s"])
    frames = []
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        rate = float(stream.average_rate or stream.guessed_rate or 30)
        for i, frame in enumerate(container.decode(stream)):
            t = float(frame.time) if frame.time is not None else i / rate
            if t >= end:
                break
            if t >= start:
                frames.append(frame.to_ndarray(format="rgb24"))
    if not frames:
        raise ValueError(f"{meta['name']}: expected frames in window_s {meta['window_s']}, got none")
    arr = np.stack(frames)
    arr = arr[:, : arr.shape[1] // 2 * 2, : arr.shape[2] // 2 * 2]  # H.264 wants even sizes
    return write_video(Path(dest) / f"{meta['name']}_trim.mp4", arr, fps=rate)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="clips to fetch (default: all)")
    ap.add_argument("--dest", default=str(DEFAULT_DEST), help="output folder (default runs/real_clips)")
    ap.add_argument("--list", action="store_true", help="list the clips, their licences and truths")
    ap.add_argument("--print", dest="print_only", action="store_true",
                    help="print the download URLs and stop")
    ap.add_argument("--trim", action="store_true", help="also write <name>_trim.mp4 (window_s)")
    args = ap.parse_args(argv)
    clips = load_clips()
    unknown = [n for n in args.names if n not in clips]
    if unknown:
        ap.error(f"names: expected some of {', '.join(clips)}, got {', '.join(unknown)}")
    chosen = [clips[n] for n in (args.names or clips)]
    if args.list or args.print_only:
        for m in chosen:
            lic = m["licence"]["spdx"] or "no licence (download only)"
            if args.print_only:
                print(m["source"]["url"])
                continue
            truths = "; ".join(f"{t['name']} {t['value']} {t['unit']}" for t in m["truths"])
            print(f"{m['name']} [{m['system']}] {m['source']['repository']}:{m['source']['path']}"
                  f" ({m['source']['bytes']} bytes, {lic}): {truths}")
        return 0
    failed = 0
    for m in chosen:
        try:
            out = download(m, args.dest)
            print(f"{m['name']}: {out}")
            if args.trim:
                print(f"{m['name']}: {trim(m, out, args.dest)}")
        except (OSError, ValueError) as exc:
            print(f"{m['name']}: {exc}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
