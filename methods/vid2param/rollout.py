"""The physical state behind Vid2Param's track, and forecasts by simulating it.

Vid2Param's latent space carries positions and parameters but no velocity. Both forecasts
(``forecast="physics"`` and the latent rollout's physics prior) need the ball's full state
``[x, y, vx, vy]`` at the last observed frame. It is a fixed function of what the network
already has -- its own filtered positions of the last ``window`` frames and its parameter
estimate -- found by fitting one simulated trajectory of ``sysid_bench.core.physics`` to those
positions (Levenberg-Marquardt on the state at the window's start, parameters held). Bounces and
walls inside the window are simulated, not cut out, so the fit uses every frame.

Positions here are floor-relative metres (``floor = 0``): the latent space's convention.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from sysid_bench.core.physics import BOX_WIDTH, DT, PARAMS, PRIOR
from sysid_bench.core.physics import simulate as _physics_simulate

__all__ = ["StateFit", "WINDOW", "HOLDOUT", "backtest_error", "clamp_state", "fit_state", "fit_track",
           "simulations", "sample_posterior",
           "sample_trajectories"]

_LO = np.array([PRIOR[p][0] for p in PARAMS])
_HI = np.array([PRIOR[p][1] for p in PARAMS])
#: Trajectories simulated by each thread (``simulations``).
_counter = threading.local()


def simulate(theta, state, n_frames, dt):
    """``sysid_bench.core.physics.simulate``, counting the trajectories (``simulations``)."""
    _counter.n = getattr(_counter, "n", 0) + len(theta)
    return _physics_simulate(theta, state, n_frames, dt)


def simulations() -> int:
    """Trajectories this thread has simulated here so far (difference two readings to count a
    fit's: every method reports the simulations it spent)."""
    return int(getattr(_counter, "n", 0))


#: Finite-difference steps of the Jacobian (m, m, m/s, m/s).
_EPS = np.array([1e-4, 1e-4, 1e-4, 1e-4])
#: Smallest position noise (m) assumed for the state's covariance: a perfect fit of a short
#: window would otherwise claim a certainty the keypoints (~5 mm on 28x28) do not have.
_MIN_SIGMA = 0.004
_Y_MIN = 1e-9  # the simulator wants the ball on or above the floor
#: Fastest speed component (m/s) a state may have: a ball launched at the prior's fastest and
#: falling the whole box moves at ~19 m/s; a fit of a few noisy frames can claim far more.
_V_MAX = 25.0
#: Largest floor offset (m) a fit may find, either way.
_FLOOR_MAX = 2.0
#: Largest std of the fitted state (m, m, m/s, m/s) in a direction the window leaves open.
_STATE_CAP = np.array([0.5, 0.5, 1.0, 1.0])
#: Largest factor by which ``fit_track`` widens its covariance for correlated residuals.
_TAU_MAX = 50.0
#: Frames fitted: 1.5 s holds a bounce or a stretch of rolling at any launch speed.
WINDOW = 30
#: Most frames a backtest holds out (``backtest_error``).
HOLDOUT = 30


@dataclass(frozen=True)
class StateFit:
    """The state fitted to a window of positions.

    Attributes
    ----------
    start : int
        Frame index of the window's first frame.
    state0 : ndarray, shape (4,)
        ``[x, y, vx, vy]`` at frame ``start`` (floor-relative metres, m/s).
    theta : ndarray, shape (4,)
        ``(e, g, d, r)`` at the fit (physical units).
    cov : ndarray, shape (9, 9)
        Covariance of ``[state0, theta, floor]`` (Laplace approximation at the fit).
    sigma : float
        RMS residual of the fit (m), at least ``_MIN_SIGMA``.
    n_used : int
        Positions fitted (visible frames of the window).
    floor : float
        The floor's height in the positions' frame; ``state0``'s y is above it.
    """

    start: int
    state0: np.ndarray
    theta: np.ndarray
    cov: np.ndarray
    sigma: float
    n_used: int
    floor: float = 0.0


def clamp_state(state: np.ndarray) -> np.ndarray:
    """States (..., 4) kept where the simulator accepts them and a real ball can be: inside the
    box, on or above the floor, speed components within ``_V_MAX``. Returns a copy."""
    s = np.array(state, dtype=np.float64, copy=True)
    s[..., 0] = np.clip(s[..., 0], 0.0, BOX_WIDTH)
    s[..., 1] = np.clip(s[..., 1], _Y_MIN, BOX_WIDTH)
    s[..., 2:4] = np.clip(s[..., 2:4], -_V_MAX, _V_MAX)
    return s


def _clamp(v: np.ndarray) -> np.ndarray:
    """State, normalised parameters and floor (..., 9) kept where the simulator accepts them."""
    v = v.copy()
    v[..., :4] = clamp_state(v[..., :4])
    v[..., 4:8] = np.clip(v[..., 4:8], 0.0, 1.0)
    v[..., 8] = np.clip(v[..., 8], -_FLOOR_MAX, _FLOOR_MAX)
    return v


def _theta(v: np.ndarray) -> np.ndarray:
    return _LO + (_HI - _LO) * v[..., 4:8]


def _starts(p: np.ndarray, valid: np.ndarray, u: np.ndarray, f0: float, dt: float) -> np.ndarray:
    """Initial guesses (K, 9): positions and velocities from the first visible frames with the
    network's parameters and the floor's prior mean, and the same with vx or vy reversed or vy
    zero (a bounce, a wall or rolling in those frames breaks a difference)."""
    idx = np.flatnonzero(valid)
    first = idx[: min(5, len(idx))]
    t = (first - first[0]) * dt
    x0, y0 = p[first[0]]
    g = _LO[1] + (_HI[1] - _LO[1]) * u[1]
    if len(first) >= 2 and t[-1] > 0:
        vx = np.polyfit(t, p[first, 0], 1)[0]
        # y = y0 + vy t + g t^2 / 2 with the network's g: one unknown, least squares
        yy = p[first, 1] - y0 - 0.5 * g * t**2
        vy = float(t @ yy / (t @ t))
    else:
        vx = vy = 0.0
    base = np.concatenate([[x0, y0 - f0, vx, vy], u, [f0]])
    flips = np.ones((4, 9))
    flips[1, 3] = -1.0
    flips[2, 2] = -1.0
    flips[3, 3] = 0.0
    return _clamp(base * flips)


def _window_start(p: np.ndarray, window: int) -> int:
    """First frame of the fitted window: the last ``window`` frames, moved earlier (by up to
    ``window`` more) while a floor or wall contact falls in its first four frames, where the
    starting guess's finite differences would straddle it."""
    T = p.shape[0]
    start = max(0, T - window)
    lowest = max(0, T - 2 * window)
    while start > lowest:
        head = p[start:start + 5]
        head = head[np.isfinite(head).all(1)]
        if len(head) < 3:
            break
        dy = np.diff(head[:, 1])
        dx = np.diff(head[:, 0])
        turns = (np.sign(dy[1:]) != np.sign(dy[:-1])).any() or (np.sign(dx[1:]) != np.sign(dx[:-1])).any()
        if not turns:
            break
        start = max(lowest, start - 5)
    return start


def fit_state(positions, theta_mean, theta_std, dt: float = DT, window: int = WINDOW,
              sigma: float | None = None, iters: int = 10,
              floor: tuple[float, float] = (0.0, 0.005)) -> StateFit:
    """MAP state and parameters given the last ``window`` positions and the network's posterior.

    Minimises ``sum |sim - pos|^2 / sigma^2 + sum ((u - u_net) / sd_net)^2`` over the state at
    the window's start and the normalised parameters ``u``: the network's posterior is the
    prior, the window's positions the likelihood. Where the window says little about a
    parameter (``r`` while the ball flies) the network's estimate stands; where it says much
    (``r`` while the ball rolls: its deceleration is in every frame) the window refines it.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
        Floor-relative positions (m); NaN rows are unseen frames.
    theta_mean, theta_std : ndarray, shape (4,)
        The network's posterior (``PARAMS`` order, physical units).
    dt : float
        Seconds between frames.
    window : int
        Frames fitted (the last ``window``, or all if fewer).
    sigma : float, optional
        Position noise (m); default: the RMS residual of a fit with the parameters held,
        at least ``_MIN_SIGMA``.
    floor : (float, float)
        Prior mean and std (m) of the floor's height in the positions' frame. A network
        trained on videos whose floor was raised by an unknown amount reads heights above
        the floor it expects, so the floor is fitted too (a bounce in the window pins it).
    iters : int
        Levenberg-Marquardt iterations from each of four starting guesses.

    Returns
    -------
    StateFit
        With fewer than three visible frames the state is the last position at rest with a
        wide covariance and the network's parameters (a forecast from it says it knows little).
    """
    p = np.asarray(positions, dtype=np.float64)
    prior = _network_prior(theta_mean, theta_std, floor)
    u_net, sd_net, f0, sd_f = prior[0][:4], prior[1][:4], prior[0][4], prior[1][4]
    span = _HI - _LO
    T = p.shape[0]
    start = _window_start(p, int(window))
    w = p[start:]
    valid = np.isfinite(w).all(1)
    n = int(valid.sum())
    if n < 3:
        last = w[valid][-1] if n else np.array([BOX_WIDTH / 2, BOX_WIDTH / 2])
        v = _clamp(np.concatenate([[last[0], last[1] - f0, 0.0, 0.0], u_net, [f0]]))
        cov = np.diag(np.concatenate([[1.0, 1.0, 16.0, 16.0], (sd_net * span) ** 2, [sd_f**2]]))
        return StateFit(T - 1, v[:4], _theta(v), cov, 1.0, n, float(v[8]))
    W = T - start
    obs = w[valid]  # (n, 2)
    # first the state alone, parameters held at the network's (a bounce early in the window
    # trades the incoming speed against e: fitted jointly from a poor start, e ran to its bound)
    starts = _starts(w, valid, u_net, f0, dt)
    held, held_cost, _ = _lm(starts, obs, valid, W, dt, 1.0, prior[0], np.full(5, 1e-9), iters)
    if sigma is None:
        sigma = max(_MIN_SIGMA, float(np.sqrt(held_cost / max(1, 2 * n - 4))))
    V, _, J = _lm(np.vstack([held, starts]), obs, valid, W, dt, sigma, *prior, iters)
    V, J, sigma, valid = _drop_misread(V, J, sigma, w, valid, dt, prior, iters)
    return _result(start, V, J, sigma, int(valid.sum()))


def fit_track(positions, theta_mean, theta_std, dt: float = DT, stage: int = 40,
              iters: int = 10, floor: tuple[float, float] = (0.0, 0.005)) -> StateFit:
    """MAP state and parameters given EVERY seen position and the network's posterior.

    ``fit_state`` over the whole track: the state at the first seen frame and the parameters,
    fitted to all positions with the network's posterior as the prior. A parameter that acts
    slowly (drag: a few percent of the speed per second) shows in a long track far more than in
    any window. One fit of 200 frames from a guess at the start falls into a wrong bounce
    sequence (a different number of bounces fits nearly as well locally), so the window grows
    from the start by ``stage`` frames at a time, each fit starting from the last: every stage
    adds at most a bounce or two to a path that already fits the frames before.

    Parameters
    ----------
    positions, theta_mean, theta_std, dt, floor
        As for ``fit_state``.
    stage : int
        Frames added per stage (the first stage fits the first ``stage`` seen frames).
    iters : int
        Levenberg-Marquardt iterations per stage.

    Returns
    -------
    StateFit
        ``start`` is the first seen frame; ``cov``'s parameter block is the posterior's
        (Laplace approximation).
    """
    p = np.asarray(positions, dtype=np.float64)
    stage = max(5, int(stage))
    seen = np.flatnonzero(np.isfinite(p).all(1))
    if len(seen) < 3:
        return fit_state(p, theta_mean, theta_std, dt=dt, window=len(p), iters=iters, floor=floor)
    start = int(seen[0])
    first = fit_state(p[:start + stage], theta_mean, theta_std, dt=dt, window=stage, iters=iters,
                      floor=floor)
    prior = _network_prior(theta_mean, theta_std, floor)
    start = first.start
    V = np.concatenate([first.state0, (first.theta - _LO) / (_HI - _LO), [first.floor]])
    sigma, J = first.sigma, None
    T = p.shape[0]
    end = start + stage
    while end < T:
        end = min(T, end + stage)
        w = p[start:end]
        valid = np.isfinite(w).all(1)
        V, _, J = _lm(V[None], w[valid], valid, end - start, dt, sigma, *prior, iters)
        V, J, sigma, valid = _drop_misread(V, J, sigma, w, valid, dt, prior, iters, reestimate=True)
    if J is None:  # the track was no longer than the first stage
        return first
    # The Laplace covariance takes the residuals as independent; the network's misreadings
    # persist over frames (a blurred ball reads low for several), so n frames carry the
    # evidence of fewer: the positions' information is divided by the residuals' integrated
    # autocorrelation time (the prior's is not: it is the network's, already calibrated).
    resid = np.where(valid[:, None], _path(V, end - start, dt) - w, np.nan)
    return _result(start, V, J, sigma, int(valid.sum()), tau=_correlation_time(resid))


def _network_prior(theta_mean, theta_std, floor) -> tuple[np.ndarray, np.ndarray]:
    """The fit's Gaussian prior on ``(u, floor)`` (5,): mean and std, from the network's
    posterior (physical units, normalised to the prior's range) and the floor's prior."""
    span = _HI - _LO
    u_net = np.clip((np.clip(np.asarray(theta_mean, float), _LO, _HI) - _LO) / span, 0, 1)
    sd_net = np.maximum(np.asarray(theta_std, float) / span, 1e-3)
    return (np.append(u_net, float(floor[0])), np.append(sd_net, max(float(floor[1]), 1e-6)))


def _correlation_time(resid: np.ndarray) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_k rho_k`` of residuals (W, 2) (NaN rows:
    unseen or dropped frames), summed over lags until the first that is not positive (the
    tail of an estimated autocorrelation is noise), at least 1 and at most ``_TAU_MAX``: the
    factor by which correlated noise inflates the variance of a fit over many frames."""
    seen = np.isfinite(resid).all(1).astype(float)
    r = np.where(seen[:, None] > 0, resid, 0.0)
    if seen.sum() < 10:
        return 1.0
    taus = []
    for c in range(r.shape[1]):  # x and y misreadings persist differently: the longer counts
        var = (r[:, c] ** 2).sum() / seen.sum()
        tau = 1.0
        for k in range(1, len(r) // 2 if var > 0 else 1):
            pairs = (seen[:-k] * seen[k:]).sum()
            if pairs < 5:
                break
            rho = (r[:-k, c] * r[k:, c]).sum() / pairs / var
            if rho <= 0:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return float(min(max(taus), _TAU_MAX))


def _drop_misread(V, J, sigma, w, valid, dt, prior, iters, reestimate=False):
    """Drop positions far outside the fit's robust spread and fit again (twice: the second
    time with the noise of the inliers' fit).

    A frame the network misread (occluded, dropped, blurred) can sit a metre off the path and
    drag the state, e and the floor with it, and inflates the noise estimate. With
    ``reestimate`` the noise is re-estimated and the fit redone even when nothing is dropped
    (a growing window's noise moves with it). Returns ``V, J, sigma, valid``.
    """
    W = len(w)
    keep = _inliers(_path(V, W, dt), w, valid)
    if (keep.sum() < valid.sum() or reestimate) and keep.sum() >= 3:
        valid, obs, n = keep, w[keep], int(keep.sum())
        for _ in range(2):
            resid = _path(V, W, dt)[valid] - obs
            sigma = max(_MIN_SIGMA, float(np.sqrt((resid**2).sum() / max(1, 2 * n - 4))))
            V, _, J = _lm(V[None], obs, valid, W, dt, sigma, *prior, iters)
    return V, J, sigma, valid


def _result(start, V, J, sigma, n, tau: float = 1.0) -> StateFit:
    """The StateFit of the fitted vector ``V`` (9,) and its whitened Jacobian ``J`` (positions'
    rows, then the prior's five), the positions' information divided by ``tau``."""
    # a direction the window does not see (vy of a rolling ball: a small hop changes no
    # position to first order) keeps at most the spread of _STATE_CAP, not an unbounded one
    cap = np.concatenate([1.0 / _STATE_CAP**2, np.zeros(5)])
    data, prior = J[:-5], J[-5:]
    info = data.T @ data / tau + prior.T @ prior
    cov = np.linalg.inv(info + np.diag(cap) + 1e-12 * np.eye(9))
    # the covariance is in (state, u, floor) coordinates: u's rows/columns to physical units
    scale = np.concatenate([np.ones(4), _HI - _LO, [1.0]])
    return StateFit(start, V[:4], _theta(V), cov * np.outer(scale, scale), float(sigma), n,
                    float(V[8]))


#: A position whose residual exceeds this many robust standard deviations of the fit's
#: residuals (and at least ``_OUTLIER_MIN`` m) is dropped as a misread frame.
_OUTLIER_Z = 5.0
_OUTLIER_MIN = 0.1


def _path(V: np.ndarray, W: int, dt: float) -> np.ndarray:
    """Positions (W, 2) of the fitted vector ``V`` (9,) in the track's frame."""
    v = _clamp(V[None])
    sim = simulate(_theta(v), v[:, :4], W, dt)[0, :, :2]
    sim[:, 1] += v[0, 8]
    return sim


def _inliers(path, w, valid) -> np.ndarray:
    """``valid`` less the positions far from the fitted ``path`` (W, 2) (robust z above
    ``_OUTLIER_Z``)."""
    dist = np.full(len(valid), np.inf)
    dist[valid] = np.linalg.norm(path[valid] - w[valid], axis=1)
    scale = 1.4826 * np.median(dist[valid])
    return valid & (dist <= max(_OUTLIER_Z * scale, _OUTLIER_MIN))


def _lm(V, obs, valid, W, dt, sigma, prior_mean, prior_sd, iters):
    """Levenberg-Marquardt from each row of ``V`` (K, 9: state, normalised parameters, floor)
    with the Gaussian prior ``prior_mean``, ``prior_sd`` (5,) on the last five; returns the
    best (9,), its cost and its whitened Jacobian (n * 2 + 5, 9)."""
    K = len(V)
    lam = np.full(K, 1e-3)
    eps = np.concatenate([_EPS, np.full(5, 1e-4)])
    D = 9

    def residuals(v):  # (M, 9) -> (M, n * 2 + 5), whitened
        v = _clamp(v)
        sim = simulate(_theta(v), v[:, :4], W, dt)[:, valid, :2]
        sim[..., 1] += v[:, 8:9]  # the simulation's floor is 0; the positions' is v[8]
        pos = (sim - obs).reshape(len(v), -1) / sigma
        return np.concatenate([pos, (v[:, 4:] - prior_mean) / prior_sd], 1)

    def jacobian(v, r0):  # (M, n*2+5, 9) by one-sided differences, one batched simulation
        # a coordinate at its bound is differenced inwards: outwards the clamp makes the
        # column zero, and the covariance would claim the parameter unknown
        h = np.where(_clamp(v + eps) != v + eps, -eps, eps)  # (M, 9)
        pert = (v[:, None, :] + h[:, :, None] * np.eye(D)[None]).reshape(-1, D)
        rp = residuals(pert).reshape(len(v), D, -1)
        return np.transpose((rp - r0[:, None, :]) / h[:, :, None], (0, 2, 1))

    r = residuals(V)
    cost = (r**2).sum(1)
    for _ in range(int(iters)):
        J = jacobian(V, r)
        JtJ = np.einsum("kni,knj->kij", J, J)
        g = np.einsum("kni,kn->ki", J, r)
        diag = np.diagonal(JtJ, axis1=1, axis2=2)
        step = -np.linalg.solve(JtJ + lam[:, None, None] * (np.eye(D) * (diag[:, None, :] + 1e-9)),
                                g[..., None])[..., 0]
        cand = _clamp(V + step)
        rc = residuals(cand)
        cc = (rc**2).sum(1)
        better = cc < cost
        V = np.where(better[:, None], cand, V)
        r = np.where(better[:, None], rc, r)
        cost = np.where(better, cc, cost)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    k = int(np.argmin(cost))
    return V[k], float(cost[k]), jacobian(V[k:k + 1], r[k:k + 1])[0]


def sample_posterior(fit: StateFit, n_samples: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint draws of the window's start state, the parameters and the floor from
    ``N([state0, theta, floor], cov)``; the state is kept in the box and the parameters in the
    prior.

    Returns
    -------
    state0 : ndarray, shape (n_samples, 4)
        Heights above each draw's floor.
    theta : ndarray, shape (n_samples, 4)
    floor : ndarray, shape (n_samples,)
    """
    L = np.linalg.cholesky(fit.cov + 1e-12 * np.eye(9))
    mean = np.concatenate([fit.state0, fit.theta, [fit.floor]])
    v = mean + rng.standard_normal((int(n_samples), 9)) @ L.T
    return clamp_state(v[:, :4]), np.clip(v[:, 4:8], _LO, _HI), v[:, 8]


def sample_trajectories(fit: StateFit, n_last: int, horizon: int, n_samples: int,
                        rng: np.random.Generator, dt: float = DT):
    """States of frames ``n_last - 1`` to ``n_last + horizon - 1`` for posterior draws.

    Each draw (``sample_posterior``) is simulated from the window's start: frame 0 of the
    result is the last observed frame, frames 1.. are the forecast.

    Returns
    -------
    states : ndarray, shape (n_samples, horizon + 1, 4)
        Metres and m/s, heights above each draw's floor.
    theta : ndarray, shape (n_samples, 4)
    floor : ndarray, shape (n_samples,)
        Each draw's floor in the positions' frame (add it to the heights).
    """
    s0, th, fl = sample_posterior(fit, n_samples, rng)
    lead = n_last - fit.start  # frames from the window's start to the first forecast frame
    sim = simulate(th, s0, lead + int(horizon), dt)
    return sim[:, lead - 1:], th, fl


def backtest_error(positions, theta_mean, theta_std, dt: float = DT,
                   floor: tuple[float, float] = (0.0, 0.005), holdout: int = HOLDOUT) -> float:
    """How well our physics forecasts this ball: the RMS distance (m) between the simulated path
    of a state fitted before the last ``holdout`` frames and the positions seen in them.

    The latent rollout's noise is scaled by it (``methods.vid2param.prior``): a ball whose
    bounces our physics misses (spin, soft contacts) shows it in the frames already seen, and
    its forecast gets wider bands than one whose past our physics predicts to the pixel.

    Parameters
    ----------
    positions : ndarray, shape (T, 2)
        Floor-relative positions (m); NaN rows are unseen frames.
    theta_mean, theta_std : ndarray, shape (4,)
        The network's posterior (physical units), as for ``fit_state``.
    holdout : int
        Frames held out: ``min(holdout, T // 2)``.

    Returns
    -------
    float
        NaN when fewer than 20 frames are given or fewer than three held-out frames are seen.
        Held-out positions that ``fit_state`` would drop as misread frames are left out.
    """
    p = np.asarray(positions, dtype=np.float64)
    T = p.shape[0]
    H = min(int(holdout), T // 2)
    if T < 20 or H < 3:
        return float("nan")
    seen = p[T - H:]
    valid = np.isfinite(seen).all(1)
    if valid.sum() < 3:
        return float("nan")
    fit = fit_state(p[:T - H], theta_mean, theta_std, dt=dt, floor=floor)
    lead = T - H - fit.start
    path = simulate(fit.theta[None], fit.state0[None], lead + H, dt)[0, lead:, :2]
    path[:, 1] += fit.floor
    # a frame the network misread (the camera model's occluded or dropped ones) is not a
    # failure of the physics: held-out positions far outside the robust spread do not count
    keep = _inliers(path, seen, valid)
    return float(np.sqrt(np.mean((path[keep] - seen[keep]) ** 2)))
