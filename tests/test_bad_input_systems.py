"""Bad input at the systems' public boundary (issue 37, "Bad input"; findings/bad-input-turn4.md,
the ``[systems:...]`` lines), one test per class, each on every registered system and on a
system a user registers (the checks live in the ``System`` base, so it gets them too)."""

from __future__ import annotations

import inspect
import sys
import types

import numpy as np
import pytest

from sysid_bench.core import systems
from sysid_bench.core.systems import System
from sysid_bench.core.testing import SystemCheckError, check_system
from sysid_bench.core.testing import system_checks as _system_checks

NAMES = ("ball", "collision", "pendulum", "spring")


class _Line(System):
    """A user's system: a point moving at speed ``v`` along x (state [x, u], u a constant
    label); no scene."""

    name = "line_probe"
    params = ("v",)
    prior = {"v": (0.5, 1.0)}
    state = ("x", "u")
    state_bounds = {"x": (-100.0, 100.0), "u": (-10.0, 10.0)}
    extent = (0.0, 10.0, -1.0, 1.0)

    def _simulate(self, theta, state0, n_frames, dt):
        t = np.arange(n_frames) * dt
        out = np.empty((state0.shape[0], n_frames, 2))
        out[..., 0] = state0[:, None, 0] + theta[:, :1, 0] * t
        out[..., 1] = state0[:, None, 1]
        return out

    def sample_state0(self, n, rng=None, theta=None):
        rng = np.random.default_rng(rng)
        return np.stack([rng.random(n), np.zeros(n)], axis=1)

    def _observe(self, states, theta):
        out = np.zeros(states.shape[:2] + (1, 2))
        out[..., 0, 0] = states[..., 0]
        return out

    def _render(self, points, states, theta, size, **nuisance):
        return np.zeros(points.shape[:2] + tuple(size), dtype=np.uint8)

    def _track(self, frames):
        return np.full((frames.shape[0], 1, 2), np.nan)


ALL = NAMES + ("user",)


def _system(name):
    return _Line() if name == "user" else systems.get(name)


def _refused(fn, *needles, exc=ValueError):
    with pytest.raises(exc) as info:
        fn()
    msg = str(info.value)
    assert "\n" not in msg, msg
    assert any(n in msg for n in needles), f"{msg!r} names none of {needles}"
    return msg


@pytest.mark.parametrize("name", ALL)
def test_simulate_refuses_empty_ragged_wrong_and_nan_input(name):
    s = _system(name)
    theta, state0 = s.sample_cases(2, 0)
    p, n = s.n_params, s.n_state
    _refused(lambda: s.simulate(np.zeros((0, p)), np.zeros((0, n)), 5), "theta", "state0")
    assert "empty" in _refused(lambda: s.simulate(np.zeros((0, p)), np.zeros((0, n)), 5), "theta")
    ragged = [list(theta[0]), list(theta[1][:-1])]
    _refused(lambda: s.simulate(ragged, state0, 5), "theta")
    _refused(lambda: s.simulate(theta, [list(state0[0]), [0.0]], 5), "state0")
    _refused(lambda: s.simulate(theta[:, :-1], state0, 5), "theta")
    _refused(lambda: s.simulate(theta[0], state0, 5), "theta")
    _refused(lambda: s.simulate(theta, state0[:, :-1], 5), "state0")
    _refused(lambda: s.simulate(theta, state0[:1], 5), "state0")
    bad = theta.copy()
    bad[1, -1] = np.nan
    _refused(lambda: s.simulate(bad, state0, 5), "theta")
    bad = state0.copy()
    bad[0, 0] = np.inf
    _refused(lambda: s.simulate(theta, bad, 5), "state0")


@pytest.mark.parametrize("name", ALL)
def test_sample_state0_refuses_negative_seeds_and_bad_theta(name):
    s = _system(name)
    _refused(lambda: s.sample_state0(2, -1), "rng")
    _refused(lambda: s.sample_state0(2, "seven"), "rng")
    _refused(lambda: s.sample_state0(0, 1), "n")
    a = s.sample_state0(3, 4)
    assert a.shape == (3, s.n_state)
    np.testing.assert_array_equal(a, s.sample_state0(3, np.random.default_rng(4)))
    if "theta" not in inspect.signature(s.sample_state0).parameters:
        return
    theta, _ = s.sample_cases(2, 0)
    _refused(lambda: s.sample_state0(2, 0, theta=theta[:, :-1]), "theta")
    _refused(lambda: s.sample_state0(3, 0, theta=theta), "theta")
    bad = theta.copy()
    bad[0, 0] = np.nan
    _refused(lambda: s.sample_state0(2, 0, theta=bad), "theta")


@pytest.mark.parametrize("name", ALL)
def test_render_refuses_huge_and_tiny_sizes_before_drawing(name):
    s = _system(name)
    theta, state0 = s.sample_cases(2, 0)
    states = s.simulate(theta, state0, 10)
    # 2 x 10 frames of 100000^2 px: 186 GiB; refused up front (no MemoryError, no allocation)
    _refused(lambda: s.render(states, theta, size=(100000, 100000)), "size")
    _refused(lambda: s.render(states, theta, size=(16000, 16000)), "size")  # 5e9 px in all
    _refused(lambda: s.render(states, theta, size=(2, 2)), "size")
    mh, mw = s.min_size
    if mh > 4 or mw > 4:
        _refused(lambda: s.render(states, theta, size=(max(4, mh - 1), max(4, mw - 1))), "size")
    assert s.render(states, theta, size=s.min_size).shape == (2, 10) + tuple(s.min_size)


@pytest.mark.parametrize("name", ALL)
def test_track_refuses_frames_too_small_to_hold_the_object(name):
    s = _system(name)
    _refused(lambda: s.track(np.zeros((5, 1, 1), np.uint8)), "frames")
    mh, mw = s.min_size
    _refused(lambda: s.track(np.zeros((5, mh - 1, mw), np.uint8)), "frames")
    _refused(lambda: s.track(np.zeros((0, mh, mw), np.uint8)), "frames")
    _refused(lambda: s.track([[[0, 1]], [[2]]]), "frames")
    assert s.track(np.zeros((3, mh, mw), np.uint8)).shape == (3, s.n_points, 2)


@pytest.mark.parametrize("name", NAMES)
def test_the_smallest_frames_still_hold_the_object(name):
    # min_size is where the round trip still works: render at it, track sees >= 80% of points
    s = systems.get(name)
    theta, state0 = s.sample_cases(2, 13)
    states = s.simulate(theta, state0, 30)
    frames = s.render(states, theta, size=s.min_size)
    seen = np.isfinite(s.track(frames[0])).all(axis=-1).mean()
    assert seen >= 0.8, seen


def test_registry_answers_a_missing_or_raising_module_naming_the_entry_point(tmp_path, monkeypatch):
    systems.register("ghost_probe", "nosuchpkg_probe.sub:Ghost")
    try:
        msg = _refused(lambda: systems.get("ghost_probe"), "nosuchpkg_probe.sub:Ghost")
        assert "ModuleNotFoundError" in msg and "ghost_probe" in msg
    finally:
        systems.unregister("ghost_probe")
    (tmp_path / "raising_probe_mod.py").write_text("raise RuntimeError('boom at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    systems.register("raising_probe", "raising_probe_mod:Thing")
    try:
        msg = _refused(lambda: systems.get("raising_probe"), "raising_probe_mod:Thing")
        assert "boom at import" in msg and "RuntimeError" in msg
    finally:
        systems.unregister("raising_probe")
    mod = types.ModuleType("empty_probe_mod")
    monkeypatch.setitem(sys.modules, "empty_probe_mod", mod)
    systems.register("empty_probe", "empty_probe_mod:Nothing")
    try:
        _refused(lambda: systems.get("empty_probe"), "Nothing")
    finally:
        systems.unregister("empty_probe")


class _Nondeterministic(_Line):
    name = "nondet_probe"
    _calls = 0

    def _simulate(self, theta, state0, n_frames, dt):
        type(self)._calls += 1
        return super()._simulate(theta, state0, n_frames, dt) + 1e-9 * type(self)._calls


class _NanObserve(_Line):
    name = "nanobs_probe"

    def _observe(self, states, theta):
        return np.full(states.shape[:2] + (1, 2), np.nan)


def _failures(system) -> list[str]:
    out = []
    for _, run in _system_checks(system):
        try:
            run()
        except SystemCheckError as exc:
            out.append(str(exc))
    return out


def test_check_system_blames_the_hook_at_fault():
    msgs = _failures(_Nondeterministic())
    assert msgs and all("nondeterministic" in m for m in msgs if "simulate" in m), msgs
    assert not any("theta differs" in m or "halving dt" in m for m in msgs), msgs
    msgs = _failures(_NanObserve())
    assert msgs and all("simulate" not in m.split(": ", 1)[1][:9] for m in msgs), msgs
    assert any("observe: non-finite positions" in m for m in msgs), msgs
    with pytest.raises(SystemCheckError, match="observe"):
        check_system(_NanObserve())
