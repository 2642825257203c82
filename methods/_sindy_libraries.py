"""``sindy`` on the systems other than the ball: one feature library per system, or n/a.

:class:`methods.sindy.SINDy` composes :class:`SINDyPoints` (this module) for a system other than
the ball; its ``systems`` declaration lists the ball and the systems of :data:`LIBRARIES`.

SINDy regresses a state's derivatives on a library of candidate features (pysindy, STLSQ). What
the library is, how the state is read from the tracked points and how the coefficients map to
the physical parameters is the system's; this module holds one :class:`Library` per system it
knows (the ball has its own hybrid :mod:`methods.sindy`):

``pendulum``
    State ``(theta, omega)`` with ``theta = atan2(x, -y)`` (unwrapped) and ``L`` the mean
    distance of the bob from the pivot. ``omega' = (g / L) sin(theta) - b omega - mu sign(omega)``:
    library ``[sin(theta), omega, sign(omega)]``; ``g = L * coef[sin]``, ``b = -coef[omega]``,
    ``mu = -coef[sign]``. Frames with ``|omega|`` below :data:`STILL_OMEGA` are left out: there
    the sign of omega is noise, and a stuck bob follows another law.
``spring``
    State ``(x, v)``. ``x'' = -w2 s - k3 s^3 - c v`` with ``s = x - L0``: library ``[s, s^3, v]``;
    ``L0`` is not a coefficient, so it is profiled: the regression's residual sum of squares is
    minimised over ``L0`` in its prior range (a grid, then a bounded scalar search), and its
    standard error comes from the profile's curvature.
``collision``
    n/a: the pucks' motion is a constant deceleration between contacts and the parameters act
    only at the contacts (mass ratio and restitution in the velocity jumps, wall restitution at
    the walls): there is no smooth vector field for a library to hold.

Derivatives are Savitzky-Golay (``smoothing_window`` frames, polynomial order 4) of the state
read from the points; standard errors are the regression's (residual variance times
``(Theta^T Theta)^-1``) inflated by ``sqrt(smoothing_window / 2)``, since smoothed derivatives of
neighbouring frames share their noise. Estimates are clipped into the prior box; a clipped
estimate's std grows by the distance moved. Forecast: the identified model (the system's
simulator) run from the state estimated at the last frame, for ``n_forecast`` draws of
parameters and state from their standard errors.

Model check (``Posterior.check``): SINDy fits derivatives, so a regression can look precise on
data its model does not explain (a frozen spring gave ``k3 = 0 +- 0``, a wrong ``dt`` a confident
pendulum). The posterior is therefore checked as the simulation methods' are
(:class:`methods._points.Problem`'s ``check`` of the system's simulator against the observed
points, with its noise :func:`~methods._points.default_sigma`): the initial state is fitted
with the parameters held at the posterior mean (:func:`~methods._points.refine` in a box
of zero width about the mean; SINDy estimates no initial state), and when that trajectory fails
the check a parameter vector inside the posterior's 90% interval may pass it (the same refine
in that box), as the ball's region check. A failed check widens every interval to at least the
prior's (``check.note``, ``extras["widened"]``). Whatever the check says, a parameter the track
cannot inform (moving it across its prior range changes the fitted trajectory by less than
``UNINFORMED_CHI2`` noise variances, as :func:`methods._simulation.uninformed` judges the
ball's), or one the regression gave no standard error (a pruned or degenerate feature), gets
at least the prior's spread (``extras["uninformed"]``): a zero std is never shown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from methods._points import (
    PointsSimulator,
    Problem,
    _system,
    default_sigma,
    forecast_points,
    prepare_points,
    refine,
)
from methods._simulation import (
    MEAN_NOTE,
    REGION_LEVEL,
    REGION_NOTE,
    UNINFORMED_CHI2,
    Stopwatch,
    make_rng,
    one_blas_thread,
)
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Check, Forecast, Observation, Posterior

__all__ = ["SINDyPoints", "LIBRARIES", "STILL_OMEGA", "CHECK_EVALS", "model_check", "na_reason"]

#: rad/s: frames of the pendulum slower than this are left out of the regression.
STILL_OMEGA = 0.3
#: residual evaluations of each least-squares refit of the model check (the initial state at
#: the posterior mean, then the region): on the 60 valid systems-experiment cases (pendulum and
#: spring, 50/100/200 frames, 1 cm noise) every check passed with 30, 97-300 simulations each
CHECK_EVALS = 30
_POLYORDER = 4


@dataclass
class _Result:
    mean: np.ndarray
    std: np.ndarray
    end_state: np.ndarray  # (S,) at the last frame
    end_std: np.ndarray  # (S,)
    extras: dict


def _savgol(y: np.ndarray, w: int, dt: float, deriv: int) -> np.ndarray:
    from scipy.signal import savgol_filter

    return savgol_filter(y, w, _POLYORDER, deriv=deriv, delta=dt, mode="interp")


def _interp_seen(y: np.ndarray) -> np.ndarray:
    """A series with NaN gaps filled linearly (the ends held)."""
    seen = np.flatnonzero(np.isfinite(y))
    return np.interp(np.arange(y.size), seen, y[seen])


def _regress(features: list, names: list, X: np.ndarray, Xdot: np.ndarray, threshold: float):
    """pysindy STLSQ of Xdot (n, 2) on the custom features of X (n, 2) (arity-2 functions).

    Returns the coefficients (2, F) and the library matrix (n, F)."""
    import pysindy as ps

    lib = ps.CustomLibrary(library_functions=features,
                           function_names=[lambda a, b, n=n: n for n in names])
    model = ps.SINDy(optimizer=ps.STLSQ(threshold=threshold), feature_library=lib)
    with one_blas_thread():
        model.fit(X, t=1.0, x_dot=Xdot)
    theta = np.column_stack([f(X[:, 0], X[:, 1]) for f in features])
    return np.asarray(model.coefficients()), theta, model


def _se(theta: np.ndarray, y: np.ndarray, coef: np.ndarray, inflation: float) -> np.ndarray:
    """Standard errors of the active coefficients of y ~ theta @ coef."""
    active = np.flatnonzero(coef != 0)
    out = np.zeros(coef.size)
    if active.size:
        resid = y - theta @ coef
        s2 = float(resid @ resid) / max(len(y) - active.size, 1)
        c = s2 * np.linalg.pinv(theta[:, active].T @ theta[:, active])
        out[active] = np.sqrt(np.maximum(np.diag(c), 0.0)) * inflation
    return out


class Library:
    """How SINDy reads one system: :meth:`fit` positions (T, K, 2) -> :class:`_Result`;
    ``window`` is its default Savitzky-Golay window (frames)."""

    window = 11

    def fit(self, pos, dt, window, threshold, system) -> _Result:  # pragma: no cover
        raise NotImplementedError


class PendulumLibrary(Library):
    features = ("sin(theta)", "omega", "sign(omega)")
    window = 15

    def fit(self, pos, dt, window, threshold, system):
        p = pos[:, 0]
        seen = np.isfinite(p).all(axis=1)
        r = np.hypot(p[seen, 0], p[seen, 1])
        L, L_se = float(np.mean(r)), float(np.std(r, ddof=1) / np.sqrt(max(r.size, 2)))
        th = np.full(len(p), np.nan)
        th[seen] = np.unwrap(np.arctan2(p[seen, 0], -p[seen, 1]))
        th = _interp_seen(th)
        om = _savgol(th, window, dt, 1)
        al = _savgol(th, window, dt, 2)
        ths = _savgol(th, window, dt, 0)
        use = seen & (np.abs(om) > STILL_OMEGA)
        if use.sum() < 10:
            raise ValueError(f"positions: the pendulum moves in {int(use.sum())} frames; "
                             "SINDy needs at least 10")
        feats = [lambda a, b: np.sin(a), lambda a, b: b, lambda a, b: np.sign(b)]
        coef, lib, model = _regress(feats, list(self.features), np.column_stack([ths, om])[use],
                                    np.column_stack([om, al])[use], threshold)
        c = coef[1]
        se = _se(lib, al[use], c, np.sqrt(window / 2.0))
        g, b, mu = c[0] * L, -c[1], -c[2]
        g_se = float(np.hypot(se[0] * L, c[0] * L_se))
        noise = 0.01 / max(L, 0.1)
        extras = {"coefficients": coef.tolist(), "features": list(self.features),
                  "equations": model.equations(), "n_used": int(use.sum())}
        return _Result(np.array([g, L, b, mu]), np.array([g_se, L_se, se[1], se[2]]),
                       np.array([ths[-1], om[-1]]), np.array([noise, 3 * noise / dt / window]),
                       extras)


class SpringLibrary(Library):
    features = ("s", "s^3", "v")
    window = 15

    def fit(self, pos, dt, window, threshold, system):
        from scipy.optimize import minimize_scalar

        x = pos[:, 0, 0]
        seen = np.isfinite(x)
        xf = _interp_seen(x)
        xs, v, a = (_savgol(xf, window, dt, k) for k in (0, 1, 2))
        xs, v, a = xs[seen], v[seen], a[seen]
        lo, hi = system.prior["L0"]

        def rss(L0):
            s = xs - L0
            th = np.column_stack([s, s**3, v])
            coef, *_ = np.linalg.lstsq(th, a, rcond=None)
            r = a - th @ coef
            return float(r @ r)

        grid = np.linspace(lo, hi, 101)
        i = int(np.argmin([rss(g) for g in grid]))
        res = minimize_scalar(rss, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, 100)]),
                              method="bounded", options={"xatol": 1e-7})
        L0 = float(res.x)
        feats = _spring_features(L0)
        coef, lib, model = _regress(feats, list(self.features), np.column_stack([xs, v]),
                                    np.column_stack([v, a]), threshold)
        c = coef[1]
        infl = np.sqrt(window / 2.0)
        se = _se(lib, a, c, infl)
        # L0's standard error from the profile: RSS(L0) - RSS_min = s^2 at one standard error
        h = 1e-3
        curv = (rss(L0 + h) - 2 * rss(L0) + rss(L0 - h)) / h**2
        s2 = rss(L0) / max(len(a) - 4, 1)
        L0_se = float(np.sqrt(2.0 * s2 / curv) * infl) if curv > 0 else (hi - lo) / np.sqrt(12)
        extras = {"coefficients": coef.tolist(), "features": list(self.features),
                  "equations": model.equations(), "n_used": int(seen.sum())}
        end_se = np.array([0.01, 3 * 0.01 / dt / window])
        return _Result(np.array([-c[0], -c[1], -c[2], L0]), np.array([se[0], se[1], se[2], L0_se]),
                       np.array([xs[-1], v[-1]]), end_se, extras)


def _spring_features(L0: float) -> list:
    """``[s, s^3, v]`` as functions of (x, v) (pysindy reads a function's arity from its
    signature, so ``L0`` is closed over, not a default argument)."""

    def s(x, v):
        return x - L0

    def s3(x, v):
        return (x - L0) ** 3

    def vel(x, v):
        return v

    return [s, s3, vel]


#: The systems SINDy has a library for (the ball: :mod:`methods.sindy`).
LIBRARIES: dict[str, Library] = {"pendulum": PendulumLibrary(), "spring": SpringLibrary()}
_NA = {
    "collision": "sindy is n/a on the collision system: the pucks decelerate at a constant rate "
                 "between contacts and every parameter acts only at a contact (mass ratio and "
                 "restitutions in the velocity jumps), so there is no smooth vector field for a "
                 "feature library to hold",
}


def _box_problem(track, sigma: float, system, lo: np.ndarray, hi: np.ndarray) -> Problem:
    """The track's :class:`Problem` with the parameters' unit box mapped onto ``[lo, hi]`` (P,)
    instead of the prior box (``lo == hi``: the parameters held, only the state fitted)."""
    prob = Problem(track, sigma, PointsSimulator(system))
    prob.plo, prob.pspan = np.asarray(lo, dtype=np.float64), np.maximum(hi - lo, 0.0)
    return prob


def _fit_in_box(prob: Problem, theta: np.ndarray, state0: np.ndarray):
    """``refine`` from ``(theta, state0)`` inside ``prob``'s box: the refitted (theta, state0)."""
    u_th = np.clip((theta - prob.plo) / np.where(prob.pspan > 0, prob.pspan, 1.0), 0.0, 1.0)
    u0 = u_th
    if prob.free:
        u0 = np.concatenate([u_th, np.clip((state0 - prob.slo) / prob.sspan, 0.0, 1.0)])
    u, _, _ = refine(prob, [u0], CHECK_EVALS)
    th, s0 = prob.split(u)
    return np.asarray(th, dtype=np.float64), np.asarray(s0, dtype=np.float64)


def model_check(post: Posterior, track) -> Posterior:
    """``post`` with its model check against ``track``; widened where it fails or where the
    track cannot inform a parameter (see the module docstring).

    Parameters
    ----------
    post : Posterior
        SINDy's answer, mean and std (P,), no samples.
    track : PointsTrack
        The observation it answers.

    Returns
    -------
    Posterior
        ``check`` set; ``extras`` gain ``check_simulations``, ``check_state0`` (S,) and, where
        widened, ``widened`` ("prior") and ``uninformed`` (the parameters' names).
    """
    system = track.system
    sigma = default_sigma(system)
    mean = np.asarray(post.mean, dtype=np.float64)
    plo, phi = system.prior_lo, system.prior_hi
    prior_std = (phi - plo) / np.sqrt(12.0)
    # the initial state that best explains the track at the posterior mean
    at_mean = _box_problem(track, sigma, system, mean, mean)
    _, s0 = _fit_in_box(at_mean, mean, track.state0)
    check = at_mean.check(mean, s0, note=MEAN_NOTE)
    n_sims = at_mean.sim.n_simulations
    theta = mean
    if not check.ok:  # a parameter vector inside the 90% interval may explain it
        lo, hi = post.interval(REGION_LEVEL)
        lo, hi = np.clip(lo, plo, phi), np.clip(hi, plo, phi)
        region = _box_problem(track, sigma, system, np.minimum(lo, hi), np.maximum(lo, hi))
        th_r, s0_r = _fit_in_box(region, mean, s0)
        n_sims += region.sim.n_simulations
        got = region.check(th_r, s0_r, note=REGION_NOTE)
        if got.ok:
            check, theta, s0 = got, th_r, s0_r
    std = np.asarray(post.std, dtype=np.float64)
    extras = {k: v for k, v in post.extras.items() if k != "check_reason"}
    extras.update(check_simulations=int(n_sims), check_state0=s0.tolist())
    if not check.ok:
        std = np.maximum(std, prior_std)
        note = "intervals widened to the prior: the model does not explain the track"
        check = Check(check.rms_m, check.noise_m, False, check.n, note)
        extras["widened"] = "prior"
    flat = _uninformed(at_mean.sim, system, theta, s0, track, sigma) | ~(std > 0)
    if flat.any():
        std = np.where(flat, np.maximum(std, prior_std), std)
        extras["uninformed"] = [p for p, f in zip(system.params, flat) if f]
    return Posterior(mean=mean, std=std, samples=post.samples, extras=extras, check=check,
                     system=post.system)


def _uninformed(sim, system, theta, state0, track, noise_m: float) -> np.ndarray:
    """Which parameters (P,) bool the track cannot inform at ``theta`` from ``state0``: each set
    to its prior's low and high end (the others held), the two trajectories' squared distance
    over the seen coordinates below ``UNINFORMED_CHI2`` noise variances (2P simulations; a
    trajectory the system refuses counts as informative)."""
    P = system.n_params
    th = np.repeat(np.asarray(theta, dtype=np.float64)[None], 2 * P, axis=0)
    for k in range(P):
        th[2 * k, k], th[2 * k + 1, k] = system.prior_lo[k], system.prior_hi[k]
    s0 = np.repeat(np.asarray(state0, dtype=np.float64)[None], 2 * P, axis=0)
    pts = sim.points(th, s0, track.n_frames, track.dt)[:, track.mask]  # (2P, n_seen, 2)
    d2 = np.sum((pts[0::2] - pts[1::2]) ** 2, axis=(1, 2))
    return np.where(np.isfinite(d2), d2 < UNINFORMED_CHI2 * float(noise_m) ** 2, False)


def na_reason(system: str) -> str:
    """Why sindy is n/a on ``system`` (a registered name without a library)."""
    return _NA.get(system, f"sindy is n/a on the {system} system: no feature library is declared "
                           "for it (methods._sindy_libraries.LIBRARIES)")


class SINDyPoints:
    """SINDy with the system's feature library (see the module docstring): the part
    :class:`methods.sindy.SINDy` composes on a system other than the ball (which checks the
    hyperparameters).

    Parameters
    ----------
    system : str
    threshold : float
        STLSQ threshold (0: plain least squares on the library; the libraries are minimal).
    smoothing_window : int, optional
        Savitzky-Golay window (odd, >= 7) of the derivatives; None: the library's (15 for
        both: on 6 spring test tracks with 1 cm noise the normalised MSE was 0.108 / 0.041 /
        0.030 / 0.056 with 7 / 11 / 15 / 21 frames; on the pendulum 9 let the noise through
        and 21 smoothed its fast swings away).
    n_forecast : int
    seed : int
    """

    min_frames = 15

    def __init__(self, *, system: str = "spring", threshold: float = 0.0,
                 smoothing_window: int | None = None, n_forecast: int = 32, seed: int = 0):
        self.system = system
        self.threshold = threshold
        self.smoothing_window = smoothing_window
        self.n_forecast = n_forecast
        self.seed = seed

    def _library(self, system) -> Library:
        lib = LIBRARIES.get(system.name)
        if lib is None:
            raise NotImplementedError(na_reason(system.name))
        return lib

    def _fit(self, obs: Observation):
        clock = Stopwatch()
        system = _system(self.system)
        lib = self._library(system)
        track = prepare_points(obs, system, self.min_frames)
        w = lib.window if self.smoothing_window is None else int(self.smoothing_window)
        if track.n_frames < w + 2:
            raise ValueError(f"obs: expected at least {w + 2} frames for a smoothing window of "
                             f"{w}, got {track.n_frames}")
        res = lib.fit(track.positions, track.dt, w, float(self.threshold), system)
        lo, hi = system.prior_lo, system.prior_hi
        prior_std = (hi - lo) / np.sqrt(12.0)
        ok = np.isfinite(res.mean)
        mean = np.where(ok, res.mean, 0.5 * (lo + hi))
        moved = np.abs(np.clip(mean, lo, hi) - mean)
        mean = np.clip(mean, lo, hi)
        std = np.where(ok & np.isfinite(res.std), np.maximum(res.std, np.minimum(moved, prior_std)),
                       prior_std)
        extras = {"n_simulations": 0, "wall_s": 0.0, "clipped": (moved > 0).tolist(),
                  **res.extras, **track.describe()}
        post = Posterior(mean=mean, std=std, samples=None, extras=extras, system=system.name)
        post = model_check(post, track)
        post.extras["wall_s"] = clock()
        return post, res, track, clock

    def identify(self, obs: Observation) -> Posterior:
        """Parameters read from the library's coefficients, model-checked (see the module);
        mean/std (P,), no samples."""
        return self._fit(obs)[0]

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """The identified model run on from the last frame's estimated state."""
        m = check_positive_int(self.n_forecast, "n_forecast")
        post, res, track, clock = self._fit(obs)
        system = track.system
        rng = make_rng(self.seed, 1)
        theta = np.clip(post.mean + post.std * rng.standard_normal((m, system.n_params)),
                        system.prior_lo, system.prior_hi)
        blo = np.array([system.state_bounds[q][0] for q in system.state])
        bhi = np.array([system.state_bounds[q][1] for q in system.state])
        s_end = np.clip(res.end_state + res.end_std * rng.standard_normal((m, system.n_state)),
                        blo, bhi)
        sim = PointsSimulator(system)
        fc = forecast_points(sim, system, theta, s_end, 1, track.dt, horizon,
                             {"posterior_extras": post.extras})
        fc.extras["wall_s"] = clock()
        return fc
