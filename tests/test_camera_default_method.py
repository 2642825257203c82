"""Which method ``identify`` uses when none is named: a frame model on the renderer's view,
emcee (else lsq) on a camera's clip, the ball included (one rule on every system)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import methods
from sysid_bench.apps import video, video_systems
from sysid_bench.core.footage import write_video


@pytest.mark.parametrize("system", ["ball", "pendulum", "spring", "collision"])
def test_a_camera_clip_defaults_to_emcee_on_every_system(system):
    assert video_systems.camera_method(system) == "emcee"


def test_without_emcee_a_camera_clip_gets_lsq(monkeypatch):
    real_get = methods.get

    def get(name, *a, **kw):
        if name == "emcee":
            raise ImportError("emcee is not installed")
        return real_get(name, *a, **kw)

    monkeypatch.setattr(methods, "get", get)
    assert video_systems.camera_method("pendulum") == "lsq"


@pytest.fixture(scope="module")
def wide_clip(tmp_path_factory):
    """A clip that is not the renderer's square view (a camera's, by its shape)."""
    path = tmp_path_factory.mktemp("clip") / "wide.mp4"
    frames = np.zeros((6, 36, 64), dtype=np.uint8)
    write_video(path, frames)
    return path


def test_the_balls_default_follows_the_view():
    sample = "docs/sample/ball.mp4"
    frame_model = video.default_method()
    assert methods.spec(frame_model).input_kind == "frames"
    assert video.ball_method(sample) == frame_model
    # a known g on the renderer's square view: still the renderer's view
    assert video.ball_method(sample, known={"g": -9.81}) == frame_model
    # a camera given: the camera's default, whatever the file
    assert video.ball_method(sample, camera={"px_per_m": 100.0}) == "emcee"


def test_a_known_g_on_a_wide_clip_is_a_camera(wide_clip):
    assert video.ball_method(wide_clip) == video.default_method()
    assert video.ball_method(wide_clip, known={"g": -9.81}) == "emcee"
    # the renderer's box given: the renderer's view, not the fall's scale
    assert video.ball_method(wide_clip, known={"g": -9.81},
                             geometry={"px_per_m": 5.0}) == video.default_method()


def test_identify_on_a_camera_clip_without_method_answers_with_emcee(tmp_path, capsys):
    """End to end: a ball thrown in front of a camera (640x360, 30 frames/s), no --method."""
    from sysid_bench.apps.cli import main
    from sysid_bench.core.camera_footage import Shot, write_clip

    clip, truth = write_clip(Shot("ball", seed=3, fps=30, duration_s=2.0, size=(360, 640),
                                  hand=False, subframes=1), tmp_path, "ball")
    out = tmp_path / "out"
    rc = main(["identify", str(clip), "--object-size-m", "0.07", "--every", "30",
               "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    info = json.load(open(out / "estimates.json"))
    assert info["method"] == "emcee"
    assert not info["resampled"]  # read at the capture's own 30 frames/s
