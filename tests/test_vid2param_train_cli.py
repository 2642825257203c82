"""The training command's bad input (issue 39): one line naming the flag and what was wrong,
before anything is built or trained (no run folder appears)."""

from __future__ import annotations

import pytest
import torch

from methods.vid2param.checkpoint import FORMAT, FORMAT_VERSION, save_atomic
from methods.vid2param.model import V2PConfig
from methods.vid2param.train import Range, TrainConfig, check_device
from sysid_bench.apps.cli import main


def _refused(capsys, tmp_path, flags, *words) -> str:
    """``sysid-bench train --out RUN flags`` exits 2 with one ``error:`` line holding ``words``,
    and leaves no run folder."""
    run = tmp_path / "run"
    argv = ["train", "--out", str(run), "--no-progress", *flags]
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    for w in words:
        assert w in err, (w, err)
    assert not run.exists()
    return err


@pytest.mark.parametrize("flags, words", [
    (["--steps", "-1"], ["--steps", "an int >= 1", "'-1'"]),
    (["--steps", "ten"], ["--steps", "'ten'"]),
    (["--p-full", "1.5"], ["--p-full", "[0, 1]"]),
    (["--lr", "0"], ["--lr", "a float > 0"]),
    (["--size", "3", "28"], ["--size", ">= 4"]),
    (["--seed", "-2"], ["--seed", "[0, 4294967295]"]),
    (["--hidden", "0"], ["--hidden", ">= 1"]),
    (["--max-minutes", "0"], ["--max-minutes", "> 0"]),
    (["--nuisance", "{blur"], ["--nuisance", "JSON"]),
    (["--bogus", "3"], ["unrecognized arguments: --bogus"]),
    (["--preset", "28x82"], ["preset", "28x28, camera", "'28x82'"]),
    (["--system", "sprung"], ["--system", "'sprung'"]),
    (["--system", "spring", "--preset", "camera"], ["--system spring", "--preset camera"]),
])
def test_a_flag_out_of_range_or_unknown_names_itself(capsys, tmp_path, flags, words):
    _refused(capsys, tmp_path, flags, *words)


@pytest.mark.parametrize("flags, words", [
    (["--batch", "64", "--chunk", "8"], ["--batch", "--chunk (8", "64"]),
    (["--steps", "20"], ["--nll-only-steps", "(600 steps)", "--steps 20"]),
    (["--system", "spring", "--steps", "50"], ["--nll-only-steps", "(6000 steps)"]),
    (["--min-obs", "30", "--n-frames", "30"], ["--min-obs", "--n-frames (30)"]),
    (["--stop-at", "5000"], ["--stop-at", "--steps (4000)"]),
    (["--time-schedule"], ["--time-schedule", "--max-minutes"]),
    (["--export-on-stop"], ["--export-on-stop", "--export PATH"]),
    (["--export-warmup", "w.pt"], ["--export-warmup", "--export PATH"]),
])
def test_flags_that_contradict_each_other_are_refused_before_training(capsys, tmp_path, flags,
                                                                       words):
    _refused(capsys, tmp_path, flags, *words)


def test_a_device_this_machine_lacks_is_refused(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    _refused(capsys, tmp_path, ["--device", "cuda"], "--device", "'cuda'", "no CUDA device")
    _refused(capsys, tmp_path, ["--device", "tpu"], "--device", "'tpu'")
    _refused(capsys, tmp_path, ["--device", "gpu please"], "--device", "'gpu please'")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a machine with one GPU
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    _refused(capsys, tmp_path, ["--device", "cuda:7"], "--device", "cuda:0 .. cuda:0", "'cuda:7'")
    assert check_device("cuda:0").type == "cuda" and check_device("auto").type == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert check_device("auto").type == "cpu" and check_device("cpu").type == "cpu"


def test_a_checkpoint_of_another_system_or_version_is_refused(capsys, tmp_path):
    # --init: the shipped ball model for a spring run
    _refused(capsys, tmp_path, ["--system", "spring", "--init", "28x28", "--nll-only-steps", "0"],
             "--init", "28x28", "ball system", "spring")
    # --init: a file of a format version this code cannot read
    future = save_atomic({"format": FORMAT, "format_version": FORMAT_VERSION + 1,
                          "config": V2PConfig().to_dict(), "state_dict": {}},
                         tmp_path / "future.pt")
    _refused(capsys, tmp_path, ["--init", str(future)], "--init", "format_version")
    # --refit: a spring command given the ball's checkpoint
    assert main(["train", "--system", "spring", "--refit", "28x28", "--export",
                 str(tmp_path / "f.pt")]) == 2
    err = capsys.readouterr().err
    assert "--refit" in err and "ball system" in err and not (tmp_path / "f.pt").exists()
    # --out: a run folder whose state is another system's is not resumed as this one
    run = tmp_path / "run"
    run.mkdir()
    save_atomic({"format": FORMAT, "format_version": FORMAT_VERSION, "optimizer": {},
                 "config": V2PConfig.preset("spring").to_dict(), "state_dict": {}, "train": {}},
                run / "state.pt")
    assert main(["train", "--out", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--out" in err and "spring system" in err and "--no-resume" in err


def test_ranges_are_declared_once_and_checked_by_the_config_too():
    ranges = Range.of(TrainConfig)
    assert ranges["steps"] == (Range(1), int) and ranges["size"] == (Range(4), int)
    assert ranges["rec_frac"] == (Range(0, 1, lo_open=True), float)
    for bad, msg in [({"batch": 0}, "batch: expected an int >= 1, got 0"),
                     ({"p_blank": -0.1}, r"p_blank: expected a float in \[0, 1\]"),
                     ({"steps": 2.5}, "steps: expected an int"),
                     ({"size": (28, 2)}, "size: expected an int >= 4, got 2"),
                     ({"clip": float("nan")}, "clip"), ({"threads": True}, "threads")]:
        with pytest.raises(ValueError, match=msg):
            TrainConfig(**bad)
