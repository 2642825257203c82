"""``check_system``: the public contract every system must meet (re-exported by
:mod:`sysid_bench.core.testing`).

Each check is independent of the others (it builds what it needs from the system and a fixed
seed), has a name ``check_system_<what>`` and raises :class:`SystemCheckError` whose message
starts with that name. :func:`system_checks` yields them one by one for a test suite that wants one
test per check.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from sysid_bench.core.systems import SUBRANGES_TEST, SUBRANGES_TRAIN, System
from sysid_bench.core.systems import get as get_system

__all__ = ["check_system", "system_checks", "SystemCheckError"]

#: frames of the trajectories the checks simulate
_T = 200
#: trajectories per check
_B = 8
#: JAX twin vs NumPy, metres
JAX_TOL_M = 1e-8
#: NumPy vs the solve_ivp reference, metres (design: <= 1e-6 m over 200 frames)
REFERENCE_TOL_M = 1e-6
#: render -> track round trip, pixels
TRACK_TOL_PX = 1.0


class SystemCheckError(AssertionError):
    """A system broke the contract; the message starts with the failing check's name."""


def _cases(system: System, n: int = _B, seed: int = 0, split=None):
    return system.sample_cases(n, np.random.default_rng(seed), split)


def check_system_declarations(system: System) -> None:
    p, s = system.params, system.state
    assert isinstance(system.name, str) and system.name, "name: expected a non-empty str"
    assert p and all(isinstance(q, str) for q in p), f"params: expected names, got {p!r}"
    assert len(set(p)) == len(p), f"params: duplicate names {p}"
    assert s and all(isinstance(q, str) for q in s), f"state: expected names, got {s!r}"
    for q in p:
        lo, hi = system.prior[q]
        assert np.isfinite([lo, hi]).all() and lo < hi, f"prior[{q!r}]: expected lo < hi, got {(lo, hi)}"
        a, b = system.envelope.get(q, (lo, hi))
        assert a <= lo and hi <= b, f"envelope[{q!r}] {(a, b)} does not hold the prior {(lo, hi)}"
    assert system.n_points >= 1, f"n_points: expected >= 1, got {system.n_points}"
    x0, x1, y0, y1 = system.extent
    assert x0 < x1 and y0 < y1, f"extent: expected x0 < x1 and y0 < y1, got {system.extent}"
    assert system.noise_m > 0, f"noise_m: expected > 0, got {system.noise_m}"


def _simulate(system: System, theta, state0, **kw) -> np.ndarray:
    """``simulate`` twice on the same input: a difference is nondeterminism, named as such
    before any check compares two different calls (and blames what differs between them)."""
    a = system.simulate(theta, state0, **kw)
    b = system.simulate(theta, state0, **kw)
    assert np.shape(a) == np.shape(b) and np.asarray(a).tobytes() == np.asarray(b).tobytes(), (
        "simulate: nondeterministic: the same theta, state0 and arguments gave different states"
    )
    return a


def _observe(system: System, states, theta) -> np.ndarray:
    """``observe`` of finite states, its positions checked finite (a NaN is observe's defect,
    not the simulator's)."""
    pts = system.observe(states, theta)
    if np.isfinite(states).all():
        bad = ~np.isfinite(np.asarray(pts, dtype=np.float64))
        assert not bad.any(), (
            f"observe: non-finite positions ({int(bad.sum())} of {bad.size} values) from finite states"
        )
    return pts


def check_system_shapes(system: System) -> None:
    theta, state0 = _cases(system, 3)
    t, p, s, k = 20, system.n_params, system.n_state, system.n_points
    states = _simulate(system, theta, state0, n_frames=t)
    assert states.shape == (3, t, s), f"simulate: expected {(3, t, s)}, got {states.shape}"
    assert states.dtype == np.float64, f"simulate: expected float64, got {states.dtype}"
    varying = np.repeat(theta[:, None, :], t, axis=1)
    same = system.simulate(varying, state0, n_frames=t)
    assert np.array_equal(same, states), "simulate: constant (B, T, P) theta differs from (B, P)"
    pts = _observe(system, states, theta)
    assert pts.shape == (3, t, k, 2), f"observe: expected {(3, t, k, 2)}, got {pts.shape}"
    frames = system.render(states, theta)
    h, w = system.size
    assert frames.shape == (3, t, h, w) and frames.dtype == np.uint8, (
        f"render: expected uint8 {(3, t, h, w)}, got {frames.dtype} {frames.shape}"
    )
    tr = system.track(frames[0])
    assert tr.shape == (t, k, 2), f"track: expected {(t, k, 2)}, got {tr.shape}"
    assert theta.shape == (3, p)


def check_system_frame0_is_state0(system: System) -> None:
    theta, state0 = _cases(system)
    states = _simulate(system, theta, state0, n_frames=5)
    assert np.array_equal(states[:, 0], state0), "simulate: frame 0 is not state0"


def check_system_same_seed_same_bytes(system: System) -> None:
    a = _cases(system, seed=3)
    b = _cases(system, seed=3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b)), "sample_*: same seed, different draws"
    s1 = system.simulate(*a, n_frames=40)
    s2 = system.simulate(*b, n_frames=40)
    assert s1.tobytes() == s2.tobytes(), "simulate: nondeterministic: same input, different bytes"
    nuis = dict(blur=0.5, occlusion=0.1, drop=0.05, noise=8.0)
    f1 = system.render(s1, a[0], seed=7, **nuis)
    f2 = system.render(s2, b[0], seed=7, **nuis)
    assert f1.tobytes() == f2.tobytes(), "render: same seed, different bytes"


def check_system_refining_dt_converges(system: System) -> None:
    theta, state0 = _cases(system, seed=5)
    coarse = _observe(system, _simulate(system, theta, state0, n_frames=101, dt=0.05), theta)
    fine = _observe(system, _simulate(system, theta, state0, n_frames=201, dt=0.025), theta)[:, ::2]
    err = float(np.abs(coarse - fine).max())
    assert err <= 1e-5, f"simulate: halving dt moved the positions by {err:.3g} m (> 1e-5 m)"


def check_system_reference(system: System) -> None:
    theta, state0 = _cases(system, 3, seed=11)
    ours = _simulate(system, theta, state0, n_frames=_T)
    _observe(system, ours, theta)
    for i in range(theta.shape[0]):
        try:
            ref = system.reference(theta[i], state0[i], n_frames=_T)
        except NotImplementedError:
            return
        d = system.observe(ours[i : i + 1], theta[i : i + 1]) - system.observe(ref[None], theta[i : i + 1])
        err = float(np.abs(d).max())
        assert err <= REFERENCE_TOL_M, (
            f"simulate vs solve_ivp reference: {err:.3g} m over {_T} frames (> {REFERENCE_TOL_M:g})"
        )


def check_system_render_track_round_trip(system: System) -> None:
    theta, state0 = _cases(system, 4, seed=13)
    states = _simulate(system, theta, state0, n_frames=60)
    pts = _observe(system, states, theta)
    frames = system.render(states, theta)
    sx, sy = (system.size[1] / (system.extent[1] - system.extent[0]),
              system.size[0] / (system.extent[3] - system.extent[2]))
    for i in range(frames.shape[0]):
        tr = system.track(frames[i])
        seen = np.isfinite(tr).all(axis=-1)
        assert seen.mean() >= 0.9, f"track: only {seen.mean():.0%} of points seen on clean video"
        px = np.abs(tr - pts[i]) * np.array([sx, sy])
        worst = float(np.nanmax(px))
        assert worst <= TRACK_TOL_PX, f"track: {worst:.2f} px from the rendered points (> 1 px)"


def check_system_jax_twin(system: System) -> None:
    if not system.jax_twin:
        raise AssertionError("jax_twin: expected the JAX twin NUTS needs, got none")
    try:
        import jax  # noqa: F401
    except ImportError:  # the twin cannot be checked without JAX; the rest still holds
        return
    f = system.jax_simulate()
    theta, state0 = _cases(system, 3, seed=17)
    ours = _simulate(system, theta, state0, n_frames=_T)
    _observe(system, ours, theta)
    for i in range(theta.shape[0]):
        twin = np.asarray(f(theta[i], state0[i], _T, 0.05))  # float64 NumPy in: twins run in x64
        d = system.observe(ours[i : i + 1], theta[i : i + 1]) - system.observe(twin[None], theta[i : i + 1])
        err = float(np.abs(d).max())
        assert err <= JAX_TOL_M, f"jax twin vs NumPy: {err:.3g} m (> {JAX_TOL_M:g})"


def check_system_default_scene(system: System) -> None:
    import dataclasses

    from sysid_bench.core.systems import Scene

    st = system.scene_type
    assert isinstance(st, type) and issubclass(st, Scene) and dataclasses.is_dataclass(st), (
        f"scene_type: expected a Scene dataclass, got {st!r}"
    )
    assert st.__dataclass_params__.frozen, f"scene_type: expected a frozen dataclass, got {st.__name__}"
    default = system.default_scene
    assert default == st() == system.scene(), "scene: the default scene is not scene_type()"
    theta, state0 = _cases(system, 3, seed=23)
    a = _simulate(system, theta, state0, n_frames=30)  # nondeterminism named first
    b = system.simulate(theta, state0, n_frames=30, scene=default)
    assert a.tobytes() == b.tobytes(), "simulate: scene=default_scene differs from scene=None"
    pa, pb = system.observe(a, theta), system.observe(a, theta, scene=default)
    assert pa.tobytes() == pb.tobytes(), "observe: scene=default_scene differs from scene=None"


def check_system_splits_leak_free(system: System) -> None:
    for split, allowed in (("train", SUBRANGES_TRAIN), ("test", SUBRANGES_TEST)):
        th = system.sample_theta(500, np.random.default_rng(19), split)
        k = np.floor(system.normalise(th) * 10).astype(int)
        bad = ~np.isin(k, allowed)
        assert not bad.any(), f"sample_theta({split!r}): values outside its tenths {allowed}"


def check_system_sensitivity_variants(system: System) -> None:
    """Experiment 4's draws (:meth:`System.sample_variant`): seeded, leak-free, and each
    condition's training data as it says (a parameter's lower half, noisy labels only in
    training, the simplified parameters held)."""
    for variant, opts in (("interleaved", {}), ("noisy", {"label_noise": 0.25}),
                          ("extrapolation", {"param": system.params[-1]})):
        a = system.sample_variant(20, 4, "train", variant, **opts)
        b = system.sample_variant(20, 4, "train", variant, **opts)
        assert all(np.array_equal(x, y) for x, y in zip(a, b)), \
            f"sample_variant({variant!r}): same seed, different draws"
    th, lab, s0, _ = system.sample_variant(20, 4, "train", "interleaved")
    th2, s02 = system.sample_cases(20, 4, "train")
    assert np.array_equal(th, th2) and np.array_equal(s0, s02) and np.array_equal(lab, th), \
        "sample_variant('interleaved') differs from sample_cases"
    th, lab, _, _ = system.sample_variant(200, 5, "train", "noisy", label_noise=0.25)
    assert not np.array_equal(lab, th), "sample_variant('noisy'): training labels without noise"
    th, lab, _, _ = system.sample_variant(50, 5, "test", "noisy", label_noise=0.25)
    assert np.array_equal(lab, th), "sample_variant('noisy'): test labels are not the truth"
    j = len(system.params) - 1
    for split in ("train", "test"):
        th, _, _, dist = system.sample_variant(200, 6, split, "extrapolation",
                                               param=system.params[j])
        u = system.normalise(th)[:, j]
        low = split == "train"
        assert (u <= 0.5 + 1e-9).all() if low else (u >= 0.5 - 1e-9).all(), \
            f"sample_variant('extrapolation', {split!r}): {system.params[j]} on the wrong side"
        assert np.allclose(dist, u - 0.5), "sample_variant('extrapolation'): distance is not " \
            "the value's distance above the training range"
    if system.simplified_params:
        th, _, _, _ = system.sample_variant(30, 7, "train", "simplified")
        for p in system.simplified_params:
            col = th[:, system.params.index(p)]
            assert np.all(col == col[0]), f"sample_variant('simplified'): {p} not held in training"
        th, _, _, _ = system.sample_variant(30, 7, "test", "simplified")
        col = th[:, system.params.index(system.simplified_params[0])]
        assert np.unique(col).size > 1, "sample_variant('simplified'): held in test too"
    _raises_value_error(lambda: system.sample_variant(3, 0, "train", "extrapolation",
                                                      param="nope"), "param", "unknown param")


def _raises_value_error(fn, needle: str, what: str) -> None:
    try:
        fn()
    except ValueError as exc:
        if needle not in str(exc):
            raise AssertionError(f"{what}: ValueError does not name {needle!r}: {exc}") from None
        return
    raise AssertionError(f"{what}: expected ValueError, got none")


def check_system_bad_input_raises(system: System) -> None:
    theta, state0 = _cases(system, 2)
    wide = np.concatenate([theta, theta[:, :1]], axis=1)
    _raises_value_error(lambda: system.simulate(wide, state0, 5), "theta", "theta of P+1 columns")
    _raises_value_error(lambda: system.simulate(wide, state0, 5), system.name, "theta of P+1 columns")
    s_wide = np.concatenate([state0, state0[:, :1]], axis=1)
    _raises_value_error(lambda: system.simulate(theta, s_wide, 5), "state0", "state0 of S+1 columns")
    far = theta.copy()
    q = system.params[0]
    a, b = system.envelope.get(q, system.prior[q])
    far[:, 0] = b + 10 * (b - a) + 1.0
    _raises_value_error(lambda: system.simulate(far, state0, 5), q, "theta outside the envelope")
    nan = theta.copy()
    nan[0, 0] = np.nan
    _raises_value_error(lambda: system.simulate(nan, state0, 5), "theta", "NaN theta")


_CHECKS: tuple[Callable[[System], None], ...] = (
    check_system_declarations,
    check_system_shapes,
    check_system_frame0_is_state0,
    check_system_same_seed_same_bytes,
    check_system_refining_dt_converges,
    check_system_reference,
    check_system_render_track_round_trip,
    check_system_jax_twin,
    check_system_default_scene,
    check_system_splits_leak_free,
    check_system_sensitivity_variants,
    check_system_bad_input_raises,
)


def system_checks(system) -> Iterator[tuple[str, Callable[[], None]]]:
    """The checks of ``system`` (a :class:`System` or a registered name) as ``(name, run)``."""
    sys_ = get_system(system)
    for fn in _CHECKS:
        def run(fn=fn):
            try:
                fn(sys_)
            except SystemCheckError:
                raise
            except AssertionError as exc:
                raise SystemCheckError(f"{fn.__name__} ({sys_.name}): {exc}") from None
            except Exception as exc:
                raise SystemCheckError(
                    f"{fn.__name__} ({sys_.name}): raised {type(exc).__name__}: {exc}"
                ) from exc

        yield fn.__name__, run


def check_system(system) -> None:
    """Run every check of the system contract; raise :class:`SystemCheckError` on the first failure.

    Parameters
    ----------
    system : System or str
        An instance or a registered name.
    """
    for _, run in system_checks(system):
        run()
