"""``physics.simulate``'s compiled input check (``_fast_inputs``) never accepts what the full
checks refuse, returns what they return, and leaves every answer bitwise the same."""

import numpy as np
import pytest

from sysid_bench.core import physics as ph


def _random_inputs(rng, B=3):
    """Valid inputs, half of them with one value pushed near or past a bound of the full
    checks (envelope, g < 0, box, speed, floor, the drag and contact step bounds)."""
    th, s0 = ph.sample_theta(B, rng), ph.sample_state0(B, rng)
    floor = [0.0, 1, float(rng.uniform(-2, 2)), rng.uniform(-2, 2, B)][rng.integers(4)]
    s0[:, 1] += np.broadcast_to(floor, (B,))
    dt = float(rng.choice([0.05, 0.2, 1.0]))
    if rng.random() < 0.5:
        b, k = rng.integers(B), rng.integers(4)
        if rng.random() < 0.5:
            lo, hi = ph.ENVELOPE[ph.PARAMS[k]]
            th[b, k] = rng.choice([lo, hi, -1e-300, 1e-9]) + rng.normal(0, 1e-3)
            if k == 2:
                th[b, k] = rng.uniform(0, 60)  # drag steps near and past DRAG_STEP
        else:
            s0[b, k] = rng.choice([-1e-9, 10.0, 10.0 + 1e-9, 100.0, 100.0 + 1e-9, np.nan,
                                   np.inf, -100.0])
    return th, s0, floor, dt


def test_the_fast_check_accepts_only_what_the_full_checks_accept():
    rng = np.random.default_rng(0)
    fast_ok = 0
    for _ in range(3000):
        th, s0, floor, dt = _random_inputs(rng)
        fast = ph._fast_inputs(th, s0, 20, dt, floor)
        try:
            full = ph._check_inputs_full(th, s0, 20, dt, floor)
        except ValueError:
            full = None
        if fast is not None:
            fast_ok += 1
            assert full is not None, (th, s0, floor, dt)
            for a, b in zip(fast, full):
                np.testing.assert_array_equal(a, b)
    assert fast_ok > 100  # the fast path was exercised, not only refused


def test_answers_and_errors_are_unchanged():
    rng = np.random.default_rng(1)
    th = ph.sample_theta(50, rng)
    s0 = ph.sample_state0(50, rng)
    fl = np.zeros(50)
    pert = np.zeros((2, 50))
    want = ph._run(*ph._check_inputs_full(th, s0, 200, ph.DT, 0.0)[:3], pert, 200, ph.DT)
    assert ph._fast_inputs(th, s0, 200, ph.DT, 0.0) is not None
    np.testing.assert_array_equal(ph.simulate(th, s0, 200, ph.DT), want)
    np.testing.assert_array_equal(ph.simulate(th, s0, 200, ph.DT, floor=fl), want)
    bad = s0.copy()
    bad[3, 2] = 150.0  # above V_MAX: the full checks' message, not a silent answer
    with pytest.raises(ValueError, match="state0: expected .vx., .vy. <= 100"):
        ph.simulate(th, bad, 200, ph.DT)
