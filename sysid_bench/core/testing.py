"""``check_estimator``: the public contract every method must meet (like scikit-learn's).

>>> import methods
>>> from sysid_bench.core.testing import check_estimator
>>> check_estimator(methods.get("prior"))          # raises on the first failure

The checks are chosen by what the method declares (:meth:`Estimator.spec`): a method that
declares ``identifies = False`` must raise ``NotImplementedError`` with a reason from
``identify``; one that declares ``forecasts = True`` must return a valid ``Forecast``; and so on.
Each check has a name (``check_<what>``); a failure raises :class:`EstimatorCheckError` whose
message starts with it. :func:`estimator_checks` yields the checks one by one, for a test suite
that wants one test per check.

The checks run the method on one seeded simulated ball (60 frames of 28x28 video with its true
positions, floor and initial state), so they take what a few identifications of the method take:
pass cheap hyperparameters (the class's ``contract_options``) for a quick run.

A method that declares other systems (``systems``: a tuple of names, or ``"any"``: every
registered system) gets one more check per system, ``check_on_system_<name>``: the same class
built with ``system=<name>`` (the other hyperparameters as given) on one seeded clip of that
system (:data:`N_OBS_SYSTEM` frames of its tracked points and its initial state,
:func:`contract_observation`) answers a posterior sized by the system (or n/a with a reason),
a forecast of its K points, the same answer twice for the same seed, and refuses the ball's
observation with a ``ValueError`` naming ``obs``. The system's own contract is
:func:`check_system`.
"""

from __future__ import annotations

import copy
import inspect
import pickle
from collections.abc import Callable, Iterator
from functools import lru_cache

import numpy as np

from sysid_bench.core.estimator import (
    MAX_HORIZON,
    POSITION_NOW,
    Estimator,
    Forecast,
    LoopStream,
    Observation,
    Posterior,
    Stream,
)
from sysid_bench.core.physics import BOX_WIDTH, PARAMS, PRIOR

__all__ = ["check_estimator", "estimator_checks", "EstimatorCheckError", "contract_observation",
           "declared_systems"]

#: frames of the observation the checks use
N_OBS = 60
#: frames of a system's observation in the per-system checks (short: they run per system)
N_OBS_SYSTEM = 40
#: forecast horizon the checks ask for
HORIZON = 10


class EstimatorCheckError(AssertionError):
    """A method broke the contract; the message starts with the failing check's name."""


@lru_cache(maxsize=1)
def _ball():
    from sysid_bench.core.physics import simulate
    from sysid_bench.core.render import render

    # one fixed, ordinary throw: bounces within the first 60 frames, stays inside the box
    theta = np.array([[0.85, -9.81, 0.01, 0.3]])
    state0 = np.array([[3.0, 7.0, 5.0, 3.5]])
    states = simulate(theta, state0, n_frames=N_OBS)
    frames = render(states)[0]
    return states[0], frames, state0[0]


@lru_cache(maxsize=8)
def _system_case(name: str):
    from sysid_bench.core import systems

    system = systems.get(name)
    rng = np.random.default_rng([N_OBS_SYSTEM, 37])
    theta = system.sample_theta(1, rng, "test")
    try:
        state0 = system.sample_state0(1, rng, theta=theta)
    except TypeError:  # a system whose start does not depend on its parameters
        state0 = system.sample_state0(1, rng)
    states = system.simulate(theta, state0, n_frames=N_OBS_SYSTEM)
    points = system.observe(states, theta)[0]
    frames = system.render(states, theta)[0]  # its renderer's view: what a frame method reads
    return points, state0[0], frames


def contract_observation(kind: str = "both", system: str = "ball") -> Observation:
    """The observation the checks use: ``"both"`` (frames, positions, floor and initial state),
    ``"frames"`` (video only) or ``"positions"`` (positions and floor).

    On a registered ``system`` without a case of its own (:data:`_OWN_CASES`):
    :data:`N_OBS_SYSTEM` frames of one seeded test-split case, its tracked points with
    (``"both"``: with its rendered frames too) or without (``"positions"``) the initial state.
    """
    own = _OWN_CASES.get(system) if isinstance(system, str) else None
    if own is not None:
        return own(kind)
    if kind not in ("both", "positions"):
        raise ValueError(f"kind: expected 'both' or 'positions' on the {system} system, "
                         f"got {kind!r}")
    points, s0, frames = _system_case(system)
    if kind == "positions":
        return Observation(positions=points.copy(), system=system)
    return Observation(frames=frames.copy(), positions=points.copy(), state0=s0.copy(),
                       system=system)


def _ball_observation(kind: str) -> Observation:
    """The ball's case: one fixed throw (:func:`_ball`) as video and positions, the floor known."""
    states, frames, s0 = _ball()
    if kind == "frames":
        return Observation(frames=frames.copy())
    if kind == "positions":
        return Observation(positions=states[:, :2].copy(), floor=0.0)
    return Observation(frames=frames.copy(), positions=states[:, :2].copy(), floor=0.0,
                       state0=s0.copy())


#: Systems whose checks use a case of their own, by kind (the ball: a throw picked to bounce
#: within :data:`N_OBS` frames, filmed, the paper's observation); the others, a user's
#: included, a seeded test-split case of the system.
_OWN_CASES = {"ball": _ball_observation}


def _fail(msg: str):
    raise AssertionError(msg)


def _clone(est: Estimator) -> Estimator:
    return type(est)(**est.get_params())


def _reason(exc: NotImplementedError) -> str:
    msg = str(exc)
    if len(msg.split()) < 4:
        _fail(f"NotImplementedError without a sentence saying why: {msg!r}")
    return msg


def _expect_value_error(fn, arg: str, what: str) -> None:
    try:
        fn()
    except ValueError as exc:
        if arg not in str(exc):
            _fail(f"{what}: ValueError does not name {arg!r}: {exc}")
        return
    except Exception as exc:  # noqa: BLE001 - anything else is the failure we report
        _fail(f"{what}: expected a ValueError naming {arg!r}, got {type(exc).__name__}: {exc}")
    _fail(f"{what}: expected a ValueError naming {arg!r}, nothing was raised")


def _check_posterior(post, where: str) -> None:
    if not isinstance(post, Posterior):
        _fail(f"{where}: expected a Posterior, got {type(post).__name__}")
    if post.mean.shape != (4,) or post.std.shape != (4,):
        _fail(f"{where}: mean/std of shape (4,) expected, got {post.mean.shape}, {post.std.shape}")
    if not np.isfinite(post.mean).all():
        _fail(f"{where}: non-finite mean {post.mean}")
    for i, p in enumerate(PARAMS):  # physical units, PARAMS order
        lo, hi = PRIOR[p]
        span = hi - lo
        if not lo - span <= post.mean[i] <= hi + span:
            _fail(f"{where}: {p} = {post.mean[i]:.4g} is far outside its prior [{lo}, {hi}]: "
                  "not physical units, or not PARAMS order")
    if post.samples is not None and (post.samples.ndim != 2 or post.samples.shape[1] != 4):
        _fail(f"{where}: samples of shape (S, 4) expected, got {post.samples.shape}")
    n = post.extras.get("n_simulations")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        _fail(f"{where}: extras['n_simulations'] must be an int >= 0, got {n!r}")
    w = post.extras.get("wall_s", None)
    if w is not None and not float(w) >= 0:
        _fail(f"{where}: extras['wall_s'] must be >= 0 seconds, got {w!r}")


def _check_forecast(fc, horizon: int, obs: Observation, where: str) -> None:
    if not isinstance(fc, Forecast):
        _fail(f"{where}: expected a Forecast, got {type(fc).__name__}")
    if fc.mean.shape != (horizon, 2) or fc.std.shape != (horizon, 2):
        _fail(f"{where}: mean/std of shape ({horizon}, 2) expected, got {fc.mean.shape}, {fc.std.shape}")
    if not np.isfinite(fc.mean).all():
        _fail(f"{where}: non-finite forecast mean")
    if fc.samples is not None and fc.samples.shape[1:] != (horizon, 2):
        _fail(f"{where}: samples of shape (S, {horizon}, 2) expected, got {fc.samples.shape}")
    # metres in the world frame: a ball moves < 1 m per frame, so the first forecast position
    # lies near the last one seen (pixels or normalised coordinates would not)
    pos = obs.positions
    last = pos[np.isfinite(pos).all(axis=1)][-1]
    gap = float(np.abs(fc.mean[0] - last).max())
    if gap > 0.2 * BOX_WIDTH:
        _fail(f"{where}: the first forecast position {fc.mean[0]} is {gap:.3g} m from the last seen "
              f"{last}: not metres in the world frame?")


def _equal(a, b, what: str) -> None:
    for field in ("mean", "std"):
        x, y = getattr(a, field), getattr(b, field)
        if not np.array_equal(x, y):
            _fail(f"{what}: {field} differs ({x} vs {y})")


# -- the checks ---------------------------------------------------------------------------------
def check_declarations(est: Estimator, ctx: dict) -> None:
    """The class's declarations are valid (``spec()``) and its name is a registry name."""
    try:
        spec = type(est).spec()
    except ValueError as exc:
        _fail(str(exc))
    if est.name != spec.name:
        _fail(f"instance name {est.name!r} differs from the class's {spec.name!r}")
    ctx["spec"] = spec


def check_constructor_stores_arguments(est: Estimator, ctx: dict) -> None:
    """Keyword-only hyperparameters with defaults, stored unchanged, a ``seed``, no work done."""
    cls = type(est)
    sig = inspect.signature(cls.__init__)
    for p in list(sig.parameters.values())[1:]:
        if p.kind is not p.KEYWORD_ONLY:
            _fail(f"hyperparameter {p.name!r} must be keyword-only")
        if p.default is p.empty:
            _fail(f"hyperparameter {p.name!r} needs a default")
    params = est.get_params()
    if "seed" not in params:
        _fail("every method takes a seed")
    fresh = cls()
    stored = fresh.get_params()  # the accessor, as scikit-learn's (an attribute may differ in name)
    for k, p in list(sig.parameters.items())[1:]:
        v = stored[k]
        if not (v is p.default or _same(v, p.default)):
            _fail(f"{k}: the constructor stored {v!r}, not the default {p.default!r} unchanged")
    again = cls(**params).get_params()
    for k, v in params.items():
        if not (again[k] is v or _same(again[k], v)):
            _fail(f"{k}: the constructor stored {again[k]!r}, given {v!r}")
    learned = [a for a in vars(fresh) if a.endswith("_") and not a.startswith("_")]
    if learned:
        _fail(f"the constructor set learned state {learned}: leave it to fit/identify")


def _same(a, b) -> bool:
    try:
        r = a == b
        return bool(np.all(r))
    except Exception:  # noqa: BLE001 - incomparable values are not the same
        return False


def check_fit_returns_self(est: Estimator, ctx: dict) -> None:
    """``fit(None)`` returns the estimator itself (learned methods load their weights)."""
    if est.fit(None) is not est:
        _fail("fit(None) must return self")


def check_bad_input_raises_value_error(est: Estimator, ctx: dict) -> None:
    """A wrong ``obs``, ``horizon`` or ``seed`` raises ValueError naming the argument."""
    obs = ctx["obs"]
    _expect_value_error(lambda: est.identify(obs.positions), "obs", "identify(array)")
    if ctx["spec"].forecasts:
        _expect_value_error(lambda: est.forecast(obs, 0), "horizon", "forecast(obs, 0)")
        _expect_value_error(lambda: est.forecast(obs, MAX_HORIZON + 1), "horizon",
                            f"forecast(obs, MAX_HORIZON + 1 = {MAX_HORIZON + 1})")
    _expect_value_error(lambda: copy.deepcopy(est).set_params(seed="x"), "seed", "set_params(seed='x')")
    _expect_value_error(lambda: type(est)(**{**est.get_params(), "seed": "x"}), "seed",
                        "constructor with seed='x'")


def check_not_implemented_has_reason(est: Estimator, ctx: dict) -> None:
    """What the method declares it cannot do raises NotImplementedError with a reason."""
    spec, obs = ctx["spec"], ctx["obs"]
    if not spec.identifies:
        try:
            est.identify(obs)
        except NotImplementedError as exc:
            _reason(exc)
        else:
            _fail("declares identifies = False but identify returned")
    if not spec.forecasts:
        try:
            est.forecast(obs, HORIZON)
        except NotImplementedError as exc:
            _reason(exc)
        else:
            _fail("declares forecasts = False but forecast returned")


def check_identify(est: Estimator, ctx: dict) -> None:
    """A Posterior of shape (4,) in physical units, PARAMS order, with the required extras."""
    _check_posterior(est.identify(ctx["obs"]), "identify")


def check_same_seed_same_answer(est: Estimator, ctx: dict) -> None:
    """Two clones with the same hyperparameters give the same posterior and forecast."""
    obs = ctx["obs"]
    a, b = _clone(est).fit(None), _clone(est).fit(None)
    if ctx["spec"].identifies:
        _equal(a.identify(obs), b.identify(obs), "identify of a clone")
    if ctx["spec"].forecasts:
        _equal(a.forecast(obs, HORIZON), b.forecast(obs, HORIZON), "forecast of a clone")


def check_pickle_round_trip(est: Estimator, ctx: dict) -> None:
    """A pickled and loaded estimator keeps its hyperparameters and gives the same answer."""
    mine = _clone(est).fit(None)
    other = pickle.loads(pickle.dumps(mine))
    if type(other) is not type(est):
        _fail(f"unpickled a {type(other).__name__}")
    back = other.get_params()
    for k, v in est.get_params().items():
        if not _same(back[k], v):
            _fail(f"{k}: {v!r} came back as {back[k]!r}")
    if ctx["spec"].identifies:
        _equal(mine.identify(ctx["obs"]), other.identify(ctx["obs"]),
               "identify after a pickle round trip")
    elif ctx["spec"].forecasts:
        _equal(mine.forecast(ctx["obs"], HORIZON), other.forecast(ctx["obs"], HORIZON),
               "forecast after a pickle round trip")


def check_clone(est: Estimator, ctx: dict) -> None:
    """``type(est)(**est.get_params())`` and ``copy.deepcopy`` keep every hyperparameter."""
    for how, other in (("clone", _clone(est)), ("deepcopy", copy.deepcopy(est))):
        back = other.get_params()
        for k, v in est.get_params().items():
            if not _same(back[k], v):
                _fail(f"{how}: {k} = {v!r} became {back[k]!r}")


def check_forecast(est: Estimator, ctx: dict) -> None:
    """A Forecast of shape (horizon, 2) in metres, continuing the track."""
    fc = est.forecast(ctx["obs"], HORIZON)
    _check_forecast(fc, HORIZON, ctx["obs"], f"forecast(obs, {HORIZON})")


def check_min_frames(est: Estimator, ctx: dict) -> None:
    """``min_frames`` frames are enough; fewer give a ValueError (not a crash) or work too."""
    spec, obs = ctx["spec"], ctx["obs"]
    n = spec.min_frames
    if n > obs.n_frames:
        _fail(f"min_frames = {n} is more than a {obs.n_frames}-frame video")
    short = obs.prefix(n)
    if spec.identifies:
        _check_posterior(est.identify(short), f"identify on min_frames = {n} frames")
    else:
        _check_forecast(est.forecast(short, HORIZON), HORIZON, short, f"forecast on {n} frames")
    if n > 1:
        try:
            (est.identify if spec.identifies else lambda o: est.forecast(o, HORIZON))(obs.prefix(n - 1))
        except ValueError:
            pass
        except Exception as exc:  # noqa: BLE001
            _fail(f"{n - 1} frames (< min_frames): expected a ValueError or an answer, got "
                  f"{type(exc).__name__}: {exc}")


def check_prefixes(est: Estimator, ctx: dict) -> None:
    """``identify_prefixes`` gives one posterior per length; a method's own
    ``identify_prefixes_batch`` gives the same means."""
    obs = ctx["obs"]
    lengths = [20, obs.n_frames]
    posts = est.identify_prefixes(obs, lengths)
    if len(posts) != len(lengths):
        _fail(f"identify_prefixes(obs, {lengths}) gave {len(posts)} posteriors")
    for n, p in zip(lengths, posts):
        _check_posterior(p, f"identify_prefixes at {n} frames")
    if type(est).identify_prefixes_batch is not Estimator.identify_prefixes_batch:
        # a method's own batched pass answers as identify_prefixes does, video by video
        batch = est.identify_prefixes_batch([obs, obs], lengths)
        if len(batch) != 2 or any(len(b) != len(lengths) for b in batch):
            _fail(f"identify_prefixes_batch([obs, obs], {lengths}): expected 2 lists of "
                  f"{len(lengths)} posteriors")
        for b in batch:
            for n, p, q in zip(lengths, posts, b):
                _check_posterior(q, f"identify_prefixes_batch at {n} frames")
                if not np.allclose(p.mean, q.mean, rtol=1e-4, atol=1e-6):
                    _fail(f"identify_prefixes_batch at {n} frames: mean {q.mean} differs from "
                          f"identify_prefixes' {p.mean}")


def check_stream(est: Estimator, ctx: dict) -> None:
    """The :class:`~sysid_bench.core.estimator.Stream` contract: a posterior after each frame, the
    frame count, the position now (2,), the latest posterior with its model check
    (``check()``) and, for a method that forecasts, a forecast with the fitted position now;
    ``online`` declared exactly when the stream is the method's own."""
    spec, obs = ctx["spec"], ctx["obs"]
    stream = est.stream()
    if not isinstance(stream, Stream):
        _fail(f"stream() returned a {type(stream).__name__}, not a Stream")
    own = not isinstance(stream, LoopStream)
    if spec.online != own:
        _fail(f"declares online = {spec.online} but stream() is "
              + ("its own" if own else "the re-identifying LoopStream"))
    stream.reset()
    if stream.n_frames != 0:
        _fail(f"n_frames after reset: expected 0, got {stream.n_frames}")
    n = max(5, spec.min_frames)
    for k, frame in enumerate(obs.frames[:n]):
        _check_posterior(stream.push(frame), f"stream.push of frame {k}")
        if stream.n_frames != k + 1:
            _fail(f"n_frames after {k + 1} pushes: got {stream.n_frames}")
    pos = np.asarray(stream.position())
    if pos.shape != (2,) or not np.isfinite(pos).all() or np.abs(pos - BOX_WIDTH / 2).max() > BOX_WIDTH:
        _fail(f"position() after {n} frames of a ball in view: expected finite metres (2,), "
              f"got {pos!r}")
    if spec.forecasts:
        fc = stream.forecast(HORIZON)
        if not isinstance(fc, Forecast) or fc.mean.shape != (HORIZON, 2):
            _fail("stream.forecast: expected a Forecast of shape (horizon, 2)")
        now = np.asarray(fc.extras.get(POSITION_NOW, np.nan), dtype=float)
        if now.shape != (2,) or not np.isfinite(now).all():
            _fail(f"stream.forecast: expected extras[{POSITION_NOW!r}] of shape (2,), got {now!r}")
        lifted = stream.forecast(HORIZON, floor=1.0)
        if not np.allclose(lifted.mean[:, 1], fc.mean[:, 1] + 1.0, atol=1e-6):
            _fail("stream.forecast(floor=1): expected the heights shifted by 1 m")
    # the latest posterior with its model check where identify checks its answers
    checked = stream.check()
    _check_posterior(checked, "stream.check")
    if checked.check is None and _clone(est).identify(obs.prefix(n)).check is not None:
        _fail("stream.check(): expected a posterior with its model check (identify checks "
              "its answers), got check None")
    _expect_value_error(lambda: stream.push(np.zeros((3, 3, 3))), "frame",
                        "stream.push of a (3, 3, 3) array")
    stream.reset()
    if stream.n_frames != 0:
        _fail(f"n_frames after a second reset: expected 0, got {stream.n_frames}")


def check_frames_only_input(est: Estimator, ctx: dict) -> None:
    """Video alone is enough: position methods track the ball themselves."""
    obs = contract_observation("frames")
    if ctx["spec"].identifies:
        _check_posterior(est.identify(obs), "identify on frames only")
    else:
        fc = est.forecast(obs, HORIZON)
        if not isinstance(fc, Forecast) or fc.mean.shape != (HORIZON, 2):
            _fail("forecast on frames only: expected a Forecast of shape (horizon, 2)")


def declared_systems(spec) -> list[str]:
    """The registered systems a method's ``spec`` declares (``"any"``: every registered one)."""
    from sysid_bench.core import systems

    known = systems.available()
    if spec.systems == "any":
        return known
    return [s for s in spec.systems if s in known]


def _on_system(est: Estimator, system: str) -> Estimator:
    if "system" not in est.get_params():
        _fail(f"declares the {system} system but takes no `system` hyperparameter to run on it")
    return type(est)(**{**est.get_params(), "system": system})


def _check_system_posterior(post, system, where: str) -> None:
    if not isinstance(post, Posterior):
        _fail(f"{where}: expected a Posterior, got {type(post).__name__}")
    P = system.n_params
    if post.system != system.name:
        _fail(f"{where}: Posterior.system {post.system!r}, expected {system.name!r}")
    if post.mean.shape != (P,) or post.std.shape != (P,):
        _fail(f"{where}: mean/std of shape ({P},) expected, got {post.mean.shape}, {post.std.shape}")
    if not (np.isfinite(post.mean).all() and np.isfinite(post.std).all()):
        _fail(f"{where}: non-finite mean {post.mean} or std {post.std}")
    span = system.prior_hi - system.prior_lo
    far = (post.mean < system.prior_lo - span) | (post.mean > system.prior_hi + span)
    if far.any():
        _fail(f"{where}: {np.asarray(system.params)[far].tolist()} = {post.mean[far]} far outside "
              "the prior: not physical units, or not the system's params order")
    if post.samples is not None and (post.samples.ndim != 2 or post.samples.shape[1] != P):
        _fail(f"{where}: samples of shape (S, {P}) expected, got {post.samples.shape}")
    n = post.extras.get("n_simulations")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        _fail(f"{where}: extras['n_simulations'] must be an int >= 0, got {n!r}")


def _check_system_forecast(fc, system, horizon: int, obs: Observation, where: str) -> None:
    if not isinstance(fc, Forecast):
        _fail(f"{where}: expected a Forecast, got {type(fc).__name__}")
    K = system.n_points
    shape = (horizon, 2) if K == 1 else (horizon, K, 2)
    if fc.mean.shape != shape or fc.std.shape != shape:
        _fail(f"{where}: mean/std of shape {shape} expected, got {fc.mean.shape}, {fc.std.shape}")
    if not np.isfinite(fc.mean).all():
        _fail(f"{where}: non-finite forecast mean")
    # metres in the system's view: the first forecast points lie near the last ones seen
    last = np.asarray(obs.points[-1]).reshape(-1, 2)
    first = np.asarray(fc.mean[0]).reshape(-1, 2)
    x0, x1, y0, y1 = system.extent
    gap = float(np.abs(first - last).max())
    if gap > 0.25 * max(x1 - x0, y1 - y0):
        _fail(f"{where}: the first forecast points {first.tolist()} are {gap:.3g} m from the last "
              f"seen {last.tolist()}: not metres in the {system.name}'s view?")


def _system_check(name: str) -> Callable[[Estimator, dict], None]:
    def check(est: Estimator, ctx: dict) -> None:
        from sysid_bench.core import systems

        system = systems.get(name)
        spec = ctx["spec"]
        obs = contract_observation("both", name)
        a, b = _on_system(est, name), _on_system(est, name)
        if spec.identifies:
            try:
                pa = a.identify(obs)
            except NotImplementedError as exc:  # n/a on this system: a sentence saying why
                _reason(exc)
                return
            _check_system_posterior(pa, system, f"identify on the {name} system")
            _equal(pa, b.identify(obs), f"identify of a clone on the {name} system")
        else:
            try:
                a.identify(obs)
            except NotImplementedError as exc:
                _reason(exc)
            else:
                _fail(f"declares identifies = False but identify returned on the {name} system")
        if spec.forecasts:
            fa = a.forecast(obs, HORIZON)
            _check_system_forecast(fa, system, HORIZON, obs, f"forecast on the {name} system")
            if not spec.identifies:  # else the fit it continues was compared above
                _equal(fa, b.forecast(obs, HORIZON), f"forecast of a clone on the {name} system")
        # a method built for this system refuses another system's observation
        _expect_value_error(lambda: a.identify(ctx["obs"]) if spec.identifies
                            else a.forecast(ctx["obs"], HORIZON), "obs",
                            f"the {name} system's method given the ball's observation")

    check.__name__ = f"check_on_system_{name}"
    check.__doc__ = (f"The method on the {name} system: a posterior sized by it (or n/a with a "
                     "reason), a forecast of its points, the same answer for the same seed, the "
                     "ball's observation refused.")
    return check


def estimator_checks(estimator: Estimator) -> Iterator[tuple[str, Callable[[], None]]]:
    """The checks that apply to ``estimator``, as ``(name, run)`` pairs.

    Each check builds what it needs (a fresh clone where it compares answers), so they may run
    in any order, alone or together.
    """
    if not isinstance(estimator, Estimator):
        raise ValueError(f"estimator: expected an Estimator instance, got {type(estimator).__name__}")
    ctx: dict = {"obs": contract_observation("both")}
    check_declarations(estimator, ctx)
    spec = ctx["spec"]
    chosen = [check_declarations, check_constructor_stores_arguments, check_clone,
              check_fit_returns_self, check_bad_input_raises_value_error,
              check_not_implemented_has_reason]
    if spec.identifies:
        chosen.append(check_identify)
    if spec.forecasts:
        chosen.append(check_forecast)
    chosen += [check_same_seed_same_answer, check_pickle_round_trip, check_min_frames]
    if spec.identifies:
        chosen += [check_prefixes, check_stream]
    chosen.append(check_frames_only_input)
    # the system of the observation the checks above used is checked by them already
    chosen += [_system_check(s) for s in declared_systems(spec) if s != ctx["obs"].system]
    for fn in chosen:
        def run(fn=fn):
            try:
                fn(estimator, ctx)
            except EstimatorCheckError:
                raise
            except AssertionError as exc:
                raise EstimatorCheckError(f"{fn.__name__} ({estimator.name}): {exc}") from None
            except Exception as exc:
                raise EstimatorCheckError(
                    f"{fn.__name__} ({estimator.name}): raised {type(exc).__name__}: {exc}"
                ) from exc

        yield fn.__name__, run


def check_estimator(estimator: Estimator) -> None:
    """Run every check that applies to ``estimator``; raise on the first failure.

    Parameters
    ----------
    estimator : Estimator
        An instance, with the hyperparameters to check (cheap ones keep it fast: the class's
        ``contract_options``).

    Raises
    ------
    EstimatorCheckError
        An ``AssertionError`` whose message starts with the failing check's name.
    ValueError
        ``estimator`` is not an Estimator instance.
    """
    for _, run in estimator_checks(estimator):
        run()


# the system contract lives beside the estimator contract (its own module keeps each short)
from sysid_bench.core._system_checks import SystemCheckError, check_system, system_checks  # noqa: E402

__all__ += ["check_system", "system_checks", "SystemCheckError"]
