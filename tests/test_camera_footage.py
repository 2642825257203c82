"""Camera-like footage of the four systems (sysid_bench.core.camera_footage): seeded bytes, a truth
consistent with the physics and the stored rotation, options identify accepts, bad shots refused."""

import argparse
import json

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core.camera_footage import SYSTEMS, Shot, film, shots, write_clip
from sysid_bench.core.footage import read_video, rotate_frames


def _tiny(system, **kw):
    base = {"system": system, "seed": 3, "fps": 30, "duration_s": 0.4, "size": (64, 96),
            "subframes": 2}
    base.update(kw)
    return Shot(**base)


@pytest.mark.parametrize("system", SYSTEMS)
def test_same_seed_same_bytes_and_a_consistent_truth(system):
    a, b = film(_tiny(system)), film(_tiny(system))
    assert a.frames.shape == (12, 64, 96, 3) and a.frames.dtype == np.uint8
    assert a.frames.tobytes() == b.frames.tobytes()
    assert film(_tiny(system, seed=4)).frames.tobytes() != a.frames.tobytes()
    tr = a.truth
    sys_ = systems.get(system)
    assert tr["params"] == list(sys_.params) and tr["n_frames"] == 12
    theta = np.array([tr["theta"][p] for p in sys_.params])
    for p, v in tr["theta"].items():
        lo, hi = sys_.prior[p]
        assert lo <= v <= hi, (p, v)
    pos = np.asarray(tr["positions_m"])
    assert pos.shape == (12, sys_.n_points, 2) and np.asarray(tr["pixels"]).shape == pos.shape
    # the last frame's positions are the physics' at its time after the release
    scene = sys_.scene(**{k: (tuple(v) if isinstance(v, list) else v)
                          for k, v in tr["scene"].items()})
    t_last = 11 / 30 - tr["release_s"]
    st = sys_.simulate(theta[None], np.asarray(tr["state0"])[None], n_frames=2, dt=t_last,
                       scene=scene)
    want = sys_.observe(st, theta[None], scene=scene)[0, 1]
    np.testing.assert_allclose(pos[-1], want, atol=1e-5)
    # the object is in the picture
    pix = np.asarray(tr["pixels"])
    assert (pix[..., 0] > 0).all() and (pix[..., 0] < 96).all()
    assert (pix[..., 1] > 0).all() and (pix[..., 1] < 64).all()


def test_stored_sideways_turns_back_with_rotate():
    up = film(_tiny("pendulum"))
    for rot in (90, 180, 270):
        side = film(_tiny("pendulum", rotate=rot))
        assert side.truth["rotate"] == rot and ["--rotate", str(rot)] == \
            side.truth["options"][4:6]
        back = np.stack([rotate_frames(side.frames[..., c], rot) for c in range(3)], axis=-1)
        assert back.tobytes() == up.frames.tobytes()


def test_write_clip_is_an_h264_file_of_the_capture_rate(tmp_path):
    v, j = write_clip(_tiny("ball", fps=60, duration_s=0.3), tmp_path, "b")
    truth = json.loads(j.read_text())
    clip = read_video(v, fps=60)
    assert clip.source_fps == pytest.approx(60) and clip.source_frames == truth["n_frames"] == 18
    assert truth["file"] == "b.mp4" and truth["object_size_m"] == pytest.approx(0.07)
    again, _ = write_clip(_tiny("ball", fps=60, duration_s=0.3), tmp_path, "b2")
    assert again.read_bytes() == v.read_bytes()  # the H.264 bytes repeat too
    slow, _ = write_clip(_tiny("spring", fps=120, duration_s=0.2, stored_fps=30.0), tmp_path, "s")
    assert read_video(slow, fps=30).source_fps == pytest.approx(30)
    assert "--fps" in json.loads((tmp_path / "s.json").read_text())["options"]


@pytest.mark.parametrize("system", ("ball", "pendulum", "spring"))
def test_the_options_a_user_would_give_are_accepted_by_identify(system):
    from sysid_bench.apps.video import add_arguments, check_options

    tr = film(_tiny(system, rotate=90)).truth
    args = add_arguments(argparse.ArgumentParser()).parse_args(["clip.mp4", *tr["options"]])
    name, known, _ = check_options(args)
    assert name == system and args.rotate == 90 and args.method == "lsq"
    if system == "pendulum":  # seed 3: g known, scale from the bob's size
        assert known == {"g": -9.81} and args.object_size_m == pytest.approx(
            tr["object_size_m"], rel=1e-2)


def test_shots_vary_rate_size_rotation_and_tilt():
    sh = shots("ball", 6)
    assert [s.fps for s in sh] == [30, 60, 120, 30, 60, 120]
    assert [s.rotate for s in sh] == [0, 90, 0, 270, 0, 0]
    assert [s.tilt_deg for s in sh][2] != 0 and sh[5].stored_fps == 30.0
    assert len({s.seed for s in sh}) == 6


@pytest.mark.parametrize("kw, exc, word", [
    ({"system": "cart"}, ValueError, "system"),
    ({"fps": 25}, ValueError, "fps"),
    ({"rotate": 45}, ValueError, "rotate"),
    ({"size": (63, 96)}, ValueError, "size"),
    ({"size": (64,)}, ValueError, "size"),
    ({"tilt_deg": 30.0}, ValueError, "tilt_deg"),
    ({"duration_s": 0.0}, ValueError, "duration_s"),
    ({"duration_s": float("nan")}, ValueError, "duration_s"),
    ({"subframes": 0}, ValueError, "subframes"),
    ({"exposure": 1.5}, ValueError, "exposure"),
    ({"stored_fps": 240.0}, ValueError, "stored_fps"),
    ({"noise": -1.0}, ValueError, "noise"),
    ({"seed": -1}, ValueError, "seed"),
    ({"seed": "1"}, TypeError, "seed"),
    ({"fps": 30.0}, TypeError, "fps"),
])
def test_bad_shots_are_refused_naming_the_argument(kw, exc, word):
    base = {"system": "ball", "size": (64, 96)}
    base.update(kw)
    with pytest.raises(exc, match=rf"^{word}: "):
        Shot(**base)


def test_film_and_shots_refuse_bad_arguments():
    with pytest.raises(TypeError, match="^shot: "):
        film({"system": "ball"})
    with pytest.raises(ValueError, match="^system: "):
        shots("cart")
    with pytest.raises(ValueError, match="^n: "):
        shots("ball", 0)


def test_the_measurement_scores_an_answer_against_the_truth():
    from scripts_loader import load_script

    m = load_script("measure_camera_footage")
    truth = {"file": "c.mp4", "system": "spring", "fps": 30, "size_filmed": [64, 96],
             "rotate": 0, "tilt_deg": 0.0, "params": ["w2", "k3", "c", "L0"],
             "theta": {"w2": 10.0, "k3": 0.0, "c": 0.1, "L0": 1.2}}
    rows = [{"w2_mean": None, "check_ok": None, "x1_m": None},
            {"w2_mean": 10.5, "w2_std": 0.25, "k3_mean": 1.0, "k3_std": 1.0, "c_mean": 0.1,
             "c_std": 0.01, "L0_mean": 1.2, "L0_std": 0.0, "check_ok": 1, "x1_m": 1.3}]
    res = {"cmd": "x", "rc": 0, "wall_s": 1.0, "estimates": {"estimates": rows}}
    row = m._score(truth, res)
    assert row["lost"] == 1 and row["frames"] == 2 and row["check_ok"] is True
    assert row["w2"]["in90"] is False and row["w2"]["z"] == pytest.approx(2.0)  # 0.5 off, 2 std
    assert row["k3"]["in90"] is True and row["k3"]["rel_err"] is None
    assert row["L0"]["z"] is None  # a held value (std 0): no z
    text = m.table([row, {**row, "rc": 2, "error": "refused", "clip": "d.mp4"}])
    assert "w2 5.0%, 0/1" in text and "exit 2: refused" in text
