"""``dmd``: time-delay (Hankel) dynamic mode decomposition of the positions (pydmd).

Plain DMD of the two coordinates has a rank-2 operator: it cannot hold a bouncing oscillation.
``pydmd.HankelDMD`` stacks ``delays`` shifted copies of the track so that a sum of damped
oscillations can represent it, and forecasts by running those modes past the last frame
(``dmd_time["tend"]`` extended). Eigenvalues outside the unit circle are projected onto it
(``pydmd.dmd_modes_tuner.stabilize_modes``) with ``stabilize=True``, so a slightly unstable mode
does not explode over a long horizon.

Unseen frames are filled by linear interpolation between seen ones (DMD needs evenly spaced
snapshots); the series starts at the first and ends at the last seen frame. Forecast spread: a
backtest. The same model is fitted without the last ``h`` frames (``h`` = min(horizon, a third of
the series)) and forecasts them; its RMS error over the first ``k`` steps is the std at step
``k`` (held constant beyond ``h``), never below the in-sample reconstruction RMS.

DMD identifies no physical parameters: ``identify`` raises ``NotImplementedError``.

On any other registered system the series is the 2K coordinates of its K tracked points
(tracked with the system's own ``track`` when only frames are given); the forecast is (H, 2)
for one point, (H, K, 2) for K > 1.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from methods._points import check_system_param, prepare_points, system_of
from methods._simulation import one_blas_thread
from sysid_bench.core.estimator import (
    Estimator,
    Forecast,
    Observation,
    Posterior,
    observed_positions,
)

__all__ = ["DMD"]


class DMD(Estimator):
    """Hankel DMD forecaster of positions.

    Parameters
    ----------
    system : str
        A registered system (:func:`sysid_bench.core.systems.available`); the class runs on any.
    delays : int
        Time-delay embedding depth ``d`` of ``HankelDMD``; 0 picks ``min(n // 2, 60)`` for a
        series of ``n`` frames.
    svd_rank : int or float
        pydmd truncation: 0 optimal hard threshold, an int >= 1 a fixed rank, a float in
        (0, 1) the fraction of energy kept (pydmd's -1, no truncation, is refused: it diverged). Default 0.99999: on 20 test tracks forecasting the
        rest of the video after 20 / 50 / 100 frames its median MSE was 41 / 15 / 11 m^2,
        against 79 / 17 / 15 for the optimal hard threshold (0) and 656 / 15 / 12 for none (-1).
        All are worse than holding the last position (14 / 10 / 7 m^2): a bouncing ball is not
        a sum of linear modes, which is what this baseline shows.
    stabilize : bool
        Project eigenvalues with modulus > 1 onto the unit circle. Without it the same forecasts
        diverge (mean MSE 8e7 m^2 after 50 frames, infinite after 20).
    seed : int
        Unused (DMD is deterministic); kept for the common interface.
    """

    name = "dmd"
    #: why ``known``/``prior`` are refused (``methods.get``; issue 38 §4)
    knowledge_refused = (
        "it identifies no parameters: a linear model of the track forecasts only")
    input_kind = "positions"
    min_frames = 3
    identifies = False
    forecasts = True
    cost = 2
    online_cost = True  # a row of the online-cost table (re-identifies every prefix)
    systems = "any"
    #: Systems whose positions are read with :func:`observed_positions` (the ball's view, with
    #: its floor); any other, a user's included, through the generic track of its K points.
    own_path = ("ball",)

    def __init__(self, *, system: str = "ball", delays: int = 0, svd_rank: float = 0.99999,
                 stabilize: bool = True, seed: int = 0):
        self.system = system
        self.delays = delays
        self.svd_rank = svd_rank
        self.stabilize = stabilize
        self.seed = seed

    def _validate(self) -> None:
        super()._validate()
        check_system_param(self)
        d = self.delays
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 0:
            raise ValueError(f"delays: expected an integer >= 0 (0 = automatic), got {d!r}")
        r = self.svd_rank
        ok = not isinstance(r, bool) and (
            (isinstance(r, (int, np.integer)) and r >= 0)
            or (isinstance(r, (float, np.floating)) and 0.0 < r < 1.0)
        )
        if not ok:
            raise ValueError(
                "svd_rank: expected 0 (optimal hard threshold), an int >= 1 (a fixed rank) or a "
                f"float in (0, 1) (the fraction of energy kept), got {r!r}"
            )
        if not isinstance(self.stabilize, (bool, np.bool_)):
            raise ValueError(f"stabilize: expected True or False, got {self.stabilize!r}")

    def identify(self, obs: Observation) -> Posterior:
        raise NotImplementedError(
            "DMD has no physical parameters to identify: it fits linear modes to the positions "
            "and can only forecast them."
        )

    def _delays(self, n: int) -> int:
        d = self.delays
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 0:
            raise ValueError(f"delays: expected an integer >= 0 (0 = automatic), got {d!r}")
        return int(d) if d else max(1, min(n // 2, 60))

    def _run(self, X: np.ndarray, n_out: int) -> tuple[np.ndarray, float]:
        """Fit on X (2, n); return the reconstruction over n + n_out frames (2, n + n_out) and
        the in-sample RMS error."""
        from pydmd import HankelDMD
        from pydmd.dmd_modes_tuner import stabilize_modes

        n = X.shape[1]
        d = min(self._delays(n), n)
        dmd = HankelDMD(svd_rank=self.svd_rank, d=d)
        with warnings.catch_warnings(), one_blas_thread():
            # a Hankel matrix of a smooth track is ill-conditioned by construction; the SVD
            # truncation is what handles it, so pydmd's condition-number warning is noise here
            warnings.simplefilter("ignore", UserWarning)
            dmd.fit(X)
            if self.stabilize:
                stabilize_modes(dmd, 1.0)
            dmd.dmd_time["tend"] = n - 1 + n_out
            rec = np.real(dmd.reconstructed_data)
        rms = float(np.sqrt(np.mean((rec[:, :n] - X) ** 2)))
        return rec, rms

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Positions of the ``horizon`` frames after the last frame of ``obs``.

        Returns
        -------
        Forecast
            mean/std (horizon, 2), no samples; ``extras`` holds ``n_simulations`` (0),
            ``wall_s``, ``delays``, ``rank`` and the ``insample_rms``/``backtest_rms`` (m).
            Another system: the points, (horizon, 2) or (horizon, K, 2) for K > 1.
        """
        t0 = time.perf_counter()
        if self.system not in self.own_path:
            return self._forecast_points(obs, horizon, t0)
        if not isinstance(obs, Observation):
            raise ValueError(f"obs: expected a sysid_bench.core.estimator.Observation, got {type(obs).__name__}")
        pos = observed_positions(obs, min_seen=3)
        mean, std, info = self._forecast_series(pos, horizon)
        extras = {
            "n_simulations": 0,
            "wall_s": time.perf_counter() - t0,
            **info,
            "input": "positions" if obs.positions is not None else "frames",
        }
        return Forecast(mean=mean, std=std, samples=None, extras=extras)

    def _forecast_points(self, obs: Observation, horizon: int, t0: float) -> Forecast:
        """The forecast of the K tracked points of a system other than the ball."""
        system = system_of(self.system)
        track = prepare_points(obs, system, self.min_frames)
        pos = track.positions.reshape(track.n_frames, -1)  # (T, 2K)
        mean, std, info = self._forecast_series(pos, horizon)
        K = system.n_points
        shape = (horizon, 2) if K == 1 else (horizon, K, 2)
        extras = {"n_simulations": 0, "wall_s": time.perf_counter() - t0, **info,
                  "input": track.input_kind}
        return Forecast(mean=mean.reshape(shape), std=std.reshape(shape), extras=extras)

    def _forecast_series(self, pos: np.ndarray, horizon: int):
        """Forecast of a series ``pos`` (T, C) of C coordinates (the ball's C = 2; a system's
        2K). A frame counts as seen when all its coordinates are.

        Returns
        -------
        mean, std : ndarray, shape (horizon, C)
        info : dict
            ``delays``, ``insample_rms`` and ``backtest_rms`` (m).
        """
        seen = np.flatnonzero(np.isfinite(pos).all(axis=1))
        first, last = int(seen[0]), int(seen[-1])
        frames = np.arange(first, last + 1)
        X = np.stack([np.interp(frames, seen, pos[seen, k]) for k in range(pos.shape[1])])  # (C, n)
        n = X.shape[1]
        skip = pos.shape[0] - 1 - last  # unseen frames at the end are still "observed" time
        rec, rms = self._run(X, skip + horizon)
        mean = rec[:, n + skip :].T

        # backtest: hide the last h frames, forecast them, measure the error growth
        h = min(horizon, n // 3)
        err = np.empty(0)
        if h >= 1 and n - h >= 3:
            rec_b, _ = self._run(X[:, : n - h], h)
            e2 = np.mean((rec_b[:, n - h :] - X[:, n - h :]) ** 2, axis=0)  # (h,)
            err = np.sqrt(np.cumsum(e2) / np.arange(1, h + 1))
        steps = np.arange(skip + horizon)
        if err.size:
            s = err[np.minimum(steps, err.size - 1)]
        else:
            s = np.full(steps.size, rms)
        s = np.maximum(s, rms)[skip:]
        if not np.isfinite(mean).all():  # an exploding mode: no forecast worth the name
            mean = np.where(np.isfinite(mean), mean, X[:, -1][None, :])
            s = np.full(horizon, np.inf)
        std = np.repeat(s[:, None], X.shape[0], axis=1)
        info = {
            "delays": min(self._delays(n), n),
            "insample_rms": rms,
            "backtest_rms": float(err[-1]) if err.size else None,
        }
        return mean, std, info
