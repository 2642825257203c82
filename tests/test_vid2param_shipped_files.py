"""The shipped Vid2Param files themselves: every checkpoint file is a registered shipped checkpoint,
none of them, nor its card, nor the model card, holds a machine path (a record of the machine it
was made on), each card is what ``export_card`` writes for its checkpoint, and the checkpoints
that ``test_vid2param_stages`` does not convert (changing, sensitivity/*) answer bitwise the same
in the stages format as in the older one."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from methods.vid2param import SHIPPED_CHECKPOINTS, Vid2Param
from methods.vid2param.checkpoint import (
    build_net,
    load_checkpoint,
    record_name,
    save_atomic,
)
from methods.vid2param.stages import LEGACY_KEYS, Pipeline

CKPT_DIR = Path(__file__).resolve().parents[1] / "methods" / "vid2param" / "checkpoints"
FILES = sorted(CKPT_DIR.rglob("*.pt"))
CARDS = sorted(CKPT_DIR.rglob("*.json"))

#: an absolute path on a machine (POSIX home, temp or work folders, a Windows drive); a leading
#: word character or dot would make it part of a relative name ("runs/x", "m/s")
MACHINE_PATH = re.compile(r"(?<![\w.])/(tmp|work|home|root|Users|mnt|scratch|var|private)(/|$)"
                          r"|\b[A-Za-z]:\\")


def _machine_paths(obj, where: str = "") -> list[str]:
    """Every string (dict keys included) in ``obj`` that holds a machine path, with where."""
    if isinstance(obj, dict):
        return [hit for k, v in obj.items()
                for hit in _machine_paths(k, f"{where}[key {k!r}]")
                + _machine_paths(v, f"{where}/{k}")]
    if isinstance(obj, (list, tuple, set)):
        return [hit for i, v in enumerate(obj) for hit in _machine_paths(v, f"{where}/{i}")]
    if isinstance(obj, bytes):
        obj = obj.decode("latin-1")
    if isinstance(obj, (str, Path)) and MACHINE_PATH.search(str(obj)):
        return [f"{where or '/'}: {str(obj)!r}"]
    return []


def test_the_scan_finds_machine_paths_wherever_they_are():
    found = _machine_paths({"a": [("x", "/tmp/p2.pt")], "/home/k": 1, "b": {"c": b"/work/x"},
                            "d": Path("/root/y"), "e": "C:\\runs\\a.pt"})
    assert len(found) == 5, found
    clean = {"init": "28x28", "from": "sensitivity/noise_0.1", "unit": "m/s", "f": "runs/camera",
             "g": "p2_28x28.pt", "h": "./tmp/x", "i": 3.0, "t": torch.zeros(2)}
    assert _machine_paths(clean) == []


def test_every_checkpoint_file_is_a_shipped_checkpoint():
    # so that every test over SHIPPED_CHECKPOINTS (the NumPy path's, the stages') sees every file
    assert FILES, f"no checkpoint files under {CKPT_DIR}"
    from methods.vid2param._points import SYSTEM_CHECKPOINTS
    from methods.vid2param.checkpoint import CONDITION_CHECKPOINTS

    systems_ = {p.resolve() for p in SYSTEM_CHECKPOINTS.values() if p.exists()}
    # the other systems' sensitivity condition models (checkpoints/sensitivity/<system>/)
    systems_ |= {p.resolve() for p in CONDITION_CHECKPOINTS.values() if p.exists()}
    assert {p.resolve() for p in FILES} == {p.resolve() for p in SHIPPED_CHECKPOINTS.values()} | systems_
    assert {p.with_suffix(".json") for p in FILES} <= set(CARDS)  # each has its card


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(CKPT_DIR)) for p in FILES])
def test_no_machine_path_in_a_shipped_checkpoint(path):
    ck = torch.load(path, map_location="cpu", weights_only=False)  # all of it, as written
    found = _machine_paths(ck)
    assert not found, f"{path.name} records machine paths:\n" + "\n".join(found)


def test_no_machine_path_in_the_cards_or_the_model_card():
    found = [f"{p.relative_to(CKPT_DIR)}{hit}" for p in CARDS
             for hit in _machine_paths(json.loads(p.read_text()))]
    readme = CKPT_DIR.parent / "README.md"
    found += [f"README.md line {i}: {ln.strip()}"
              for i, ln in enumerate(readme.read_text().splitlines(), 1) if MACHINE_PATH.search(ln)]
    assert not found, "machine paths:\n" + "\n".join(found)


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(CKPT_DIR)) for p in FILES])
def test_each_card_is_what_export_card_writes_for_its_checkpoint(path, tmp_path):
    from methods.vid2param.train import export_card

    copy = tmp_path / path.name
    shutil.copyfile(path, copy)
    written = json.loads(export_card(copy).read_text())
    card = json.loads(path.with_suffix(".json").read_text())
    assert card["file_bytes"] == path.stat().st_size
    differ = sorted(k for k in set(card) | set(written) if card.get(k) != written.get(k))
    assert not differ, f"{path.with_suffix('.json').name} is stale in {differ}"


def test_records_name_shipped_checkpoints_by_name():
    from methods.vid2param.train import _resolve_init, init_record

    path = SHIPPED_CHECKPOINTS["28x28"]
    assert record_name("28x28") == "28x28"
    assert record_name(path) == record_name(str(path)) == "28x28"
    assert record_name(path.parent / "sensitivity" / ".." / path.name) == "28x28"
    assert record_name("runs/mine.pt") == "runs/mine.pt"  # not shipped: as given
    assert _resolve_init(str(path)) == "28x28" and _resolve_init("none") is None
    assert init_record(str(path))["path"] == "28x28"


#: the shipped checkpoints that tests/test_vid2param_stages.py does not convert bitwise
OTHERS = [n for n in SHIPPED_CHECKPOINTS if n not in ("28x28", "camera")]


@pytest.mark.parametrize("name", OTHERS)
def test_the_other_checkpoints_answer_bitwise_the_same_in_the_stages_format(name, tmp_path):
    from sysid_bench.core.datasets import make_dataset

    src = SHIPPED_CHECKPOINTS[name]
    ck = dict(load_checkpoint(src))
    pipe = Pipeline.from_checkpoint(ck, src, build_net(ck, src))
    for key in LEGACY_KEYS:
        ck.pop(key, None)
    ck["stages"] = pipe.records()
    save_atomic(ck, tmp_path / "staged.pt")
    old = Vid2Param(checkpoint=name, device="cpu", n_samples=8, threads=1)
    new = Vid2Param(checkpoint=tmp_path / "staged.pt", device="cpu", n_samples=8, threads=1)
    frames = np.asarray(make_dataset("test", 2, 31, size=old.frame_size, n_frames=40).frames)
    for a, b in zip(old.normalised_prefixes(frames, [20, 40]),
                    new.normalised_prefixes(frames, [20, 40])):
        np.testing.assert_array_equal(a, b)
    sa, sb = old.stream(), new.stream()
    for f in frames[0]:
        pa, pb = sa.push(f), sb.push(f)
        np.testing.assert_array_equal(pa.mean, pb.mean)
        np.testing.assert_array_equal(pa.std, pb.std)
    np.testing.assert_array_equal(sa.forecast(10).samples, sb.forecast(10).samples)
