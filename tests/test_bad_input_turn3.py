"""Bad input, turn 3 (issue 29): one test per class of defect in
``shared/findings/bad-input-turn3.md``; ``docs/reliability.md`` ("Bad input, turn 3") maps
each line of the findings to its class.

Every refusal must be a ``ValueError`` (or, on the command line, one ``error`` line and a
non-zero exit) whose message names the input.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

import methods
from sysid_bench.apps import cli
from sysid_bench.core import physics
from sysid_bench.core.estimator import Forecast, Observation, Posterior, prior_posterior


def _refused(fn, name: str) -> str:
    """``fn()`` raises ValueError naming ``name``; returns the message."""
    with pytest.raises(ValueError) as info:
        fn()
    msg = str(info.value)
    assert name in msg, f"the error does not name {name!r}: {msg}"
    return msg


def _one_line_error(capsys, argv, *names) -> str:
    """``sysid-bench argv`` exits non-zero with one line on stderr naming each of ``names``."""
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse's own refusal
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert rc not in (0, None), f"{argv} exited 0"
    assert "Traceback" not in err, err
    last = err.splitlines()[-1] if err else ""
    for n in names:
        assert n in last, f"{argv}: {n!r} not in {last!r}"
    return last


def _track(n=40):
    th = np.array([[0.8, -9.81, 0.02, 0.35]])
    s0 = np.array([[2.0, 7.0, 5.0, 3.0]])
    return physics.simulate(th, s0, n)[0, :, :2]


# -- class 1: a value of the wrong type taken (str / bool as a number, float as an int, a truthy
# string as a flag, a bool array as positions) ----------------------------------------------------
def test_types_are_checked_alike_at_every_boundary():
    th = np.array([[0.8, -9.81, 0.02, 0.35]])
    s0 = np.array([[2.0, 7.0, 5.0, 3.0]])
    _refused(lambda: physics.simulate(th, s0, 20, dt="0.05"), "dt")
    _refused(lambda: physics.simulate(th, s0, 20, dt=True), "dt")
    _refused(lambda: physics.sample_theta(3, 0, subranges=[0.5]), "subranges")
    _refused(lambda: Observation(positions=np.ones((10, 2), dtype=bool)), "positions")
    _refused(lambda: prior_posterior(n_samples=2.5), "n_samples")
    for name, opts, bad in [
        ("lsq", {"sigma": "0.02"}, "sigma"),
        ("lsq", {"sigma": True}, "sigma"),
        ("emcee", {"progress": "no"}, "progress"),
        ("nuts", {"target_accept": "0.8"}, "target_accept"),
        ("nuts", {"dense_mass": "yes"}, "dense_mass"),
        ("vid2param", {"checkpoint": 123}, "checkpoint"),
        ("vid2param", {"clip": "no"}, "clip"),
        ("vid2param-physics", {"warm_start": "no"}, "warm_start"),
        ("dmd", {"stabilize": "no"}, "stabilize"),
    ]:
        _refused(lambda name=name, opts=opts: methods.get(name, **opts), bad)
    from sysid_bench.apps.intercept import Scene
    from sysid_bench.bench.runner import run

    _refused(lambda: run(scale="smoke", methods=["prior"], progress="no"), "progress")
    _refused(lambda: Scene(min_swing=True), "min_swing")
    # a hyperparameter changed on the instance is checked where it is used
    est = methods.get("lsq", n_samples=100)
    est.sigma = "0.02"
    obs = Observation(positions=_track(), floor=0.0)
    _refused(lambda: est.identify(obs), "sigma")


# -- class 2: a physically impossible value accepted at one boundary that simulate refuses ------
def test_physical_envelopes_are_the_same_at_every_boundary():
    pos = _track()
    _refused(lambda: Observation(positions=pos + [0.0, 1e300], floor=1e300), "floor")
    _refused(lambda: Observation(positions=pos, floor=0.0, state0=[2.0, 7.0, 1e6, 0.0]), "state0")
    _refused(lambda: Posterior(mean=[5.0, 100.0, -1.0, -3.0], std=[0.1, 0.5, 0.01, 0.1]), "mean")
    _refused(lambda: Forecast(mean=np.zeros((0, 2)), std=np.zeros((0, 2))), "mean")
    # what is within them still passes: a mean a little past the envelope (an unclipped network)
    Posterior(mean=[1.02, -9.8, 0.02, 0.3], std=[0.1, 0.5, 0.01, np.inf])
    Observation(positions=pos, floor=0.0, state0=[2.0, 7.0, 99.0, 0.0])


# -- class 3: set_params keeps what it refused, or keeps state of the old value -----------------
def test_set_params_keeps_nothing_it_refused_and_drops_what_a_change_invalidates():
    est = methods.get("lsq", n_samples=100)
    _refused(lambda: est.set_params(seed=-1), "seed")
    assert est.seed == 0
    _refused(lambda: est.set_params(n_samples=50, sigma="x"), "sigma")
    assert est.get_params()["n_samples"] == 100 and est.sigma is None  # None: DEFAULT_SIGMA
    est.identify(Observation(positions=_track(), floor=0.0))  # still usable
    v = methods.get("vid2param")
    v2 = copy.deepcopy(v)
    _refused(lambda: v2.set_params(forecast="nonsense"), "forecast")
    assert v2.forecast_kind is None
    assert v.frame_size == (28, 28)
    v.set_params(checkpoint="camera")
    assert v.frame_size != (28, 28)  # the camera network is loaded, not the 28x28 one kept


# -- class 4: an error raised from inside a library, or of another type, not naming the input --
def test_every_refusal_is_a_value_error_naming_the_input():
    _refused(lambda: physics.simulate(np.zeros((1, 4)) + [0.8, -9.81, 0.02, 0.3],
                                      [[2.0, 7.0, 1.0, 1.0]], n_frames=10**9), "n_frames")
    _refused(lambda: physics.normalise_theta(np.zeros((2, 3))), "theta")
    _refused(lambda: physics.normalise_theta([["a", "b", "c", "d"]]), "theta")
    _refused(lambda: physics.denormalise_theta(np.zeros((2, 3))), "u")
    _refused(lambda: Posterior(mean=[0.8, -9.8, 0.02, 0.3], std=["a", "b", "c", "d"]), "std")
    _refused(lambda: prior_posterior().interval("0.9"), "level")
    _refused(lambda: prior_posterior(n_samples=-1), "n_samples")
    methods.register("ghost_probe", "methods.ghost:Ghost")
    try:
        _refused(lambda: methods.get("ghost_probe"), "methods.ghost")
    finally:
        methods.unregister("ghost_probe")
    _refused(lambda: methods.get("nuts", seed=2**70), "seed")
    for name in ("vid2param", "vid2param-physics", "vid2param-changing"):
        _refused(lambda name=name: methods.get(name, seed=np.random.default_rng(0)), "seed")
    obs = Observation(positions=_track(), floor=0.0)
    lsq = methods.get("lsq", n_samples=100)
    _refused(lambda: lsq.identify_prefixes(obs, "abc"), "lengths")
    _refused(lambda: lsq.fit("string"), "train")
    _refused(lambda: lsq.fit(np.zeros((2, 10, 28, 28))), "train")
    obs.positions = "abc"  # changed after it was made
    _refused(lambda: lsq.identify(obs), "positions")
    # an empty batch is valid: no balls in, no trajectories out
    assert physics.simulate(np.zeros((0, 4)), np.zeros((0, 4)), 10).shape == (0, 10, 4)


# -- class 5: an unwritable output answered with an OSError traceback -------------------------
def test_unwritable_outputs_are_one_line_naming_the_path(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    _one_line_error(capsys, ["run", "--scale", "smoke", "--methods", "prior", "--experiments",
                             "identification", "--run-dir", "afile/run", "--workers", "0",
                             "--no-progress"], "afile")
    _one_line_error(capsys, ["intercept", "--policy", "oracle", "--throws", "1", "--out",
                             "afile/x", "--no-progress"], "afile")


# -- class 6: a corrupt store accepted, or answered with an sqlite traceback; a full disk ------
def _small_store(path):
    from sysid_bench.bench.store import Row, Store

    with Store(path, grid_config={"probe": 1}) as st:
        for c in range(60):
            key = {"experiment": "x", "method": "m", "input": "positions", "case": c}
            st.add_cell(f"c{c}", key, [Row(c, n, f"metric{k}", float(k))
                                       for n in range(5) for k in range(10)])
    return path


@pytest.mark.parametrize("damage", ["garbage-middle", "truncate-half", "garbage-header", "text"])
def test_a_corrupt_store_is_refused_with_one_line_saying_what_to_do(tmp_path, capsys, damage):
    from sysid_bench.bench.store import Store

    path = _small_store(tmp_path / "results.sqlite")
    data = bytearray(path.read_bytes())
    page = 4096
    if damage == "garbage-middle":
        mid = (len(data) // page // 2) * page
        data[mid:mid + page] = np.random.default_rng(0).integers(0, 256, page, np.uint8).tobytes()
    elif damage == "truncate-half":
        data = data[: (len(data) // page // 2) * page]
    elif damage == "garbage-header":
        data[:100] = b"\x17" * 100
    else:
        data = bytearray(b"not a database\n" * 100)
    path.write_bytes(bytes(data))
    msg = _refused(lambda: Store(path), str(path))
    assert "corrupt" in msg and ("--run-dir" in msg or "delete" in msg or "move" in msg), msg
    _one_line_error(capsys, ["report", "--from-store", str(path), "--out", str(tmp_path / "r")],
                    str(path))


def test_a_full_disk_says_disk_full_and_keeps_the_cells_stored(tmp_path):
    from sysid_bench.bench.store import Row, Store

    path = tmp_path / "results.sqlite"
    st = Store(path, grid_config={"probe": 1})
    key = {"experiment": "x", "method": "m", "input": "positions", "case": 0}
    st.add_cell("c0", key, [Row(0, 0, "a", 1.0)])
    pages = st._con.execute("PRAGMA page_count").fetchone()[0]
    st._con.execute(f"PRAGMA max_page_count={pages + 1}")  # what a full disk looks like to SQLite
    rows = [Row(1, n, f"metric{k}", float(k)) for n in range(50) for k in range(50)]
    with pytest.raises(OSError) as info:
        st.add_cell("c1", {**key, "case": 1}, rows)
    assert "disk full" in str(info.value) and str(path) in str(info.value)
    st.close()
    assert Store(path).done_cells() == {"c0"}


# -- class 7: a command-line option out of range accepted, or refused with a traceback --------
def test_command_line_options_are_range_checked(capsys, tmp_path):
    for opt, val in [("--catch-radius", "1e9"), ("--speed", "inf"), ("--speed", "1e300"),
                     ("--draw", "-1"), ("--throws", "0")]:
        _one_line_error(capsys, ["intercept", "--policy", "oracle", opt, val,
                                 "--out", str(tmp_path)], opt.lstrip("-"))
    _one_line_error(capsys, ["intercept", "--policy", "oracle", "--throws", "5", "--draw", "999",
                             "--out", str(tmp_path), "--no-progress"], "draw")
    _one_line_error(capsys, ["identify", "v.mp4", "--horizon", "100000"], "horizon")
    _one_line_error(capsys, ["run", "--scale", "smoke", "--methods", "prior", "--inline", "bogus",
                             "--run-dir", str(tmp_path / "r"), "--no-progress"], "bogus")
    _one_line_error(capsys, ["train", "--out", str(tmp_path / "t"), "--steps", "-1"], "steps")
    _one_line_error(capsys, ["evaluate", "--n", "0"], "n")
    from sysid_bench.apps.video import geometry_from_options

    _refused(lambda: geometry_from_options((28, 28), px_per_m=1e-6), "px_per_m")
