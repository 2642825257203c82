"""The controller interface and the policies built on the suite's own pieces (oracle, random,
react, the stream and re-identifying policies)."""

from __future__ import annotations

import numpy as np

from sysid_bench.bench.intercept.scene import _FINE, Scene, Throw, crossing_from_forecast
from sysid_bench.core._validate import check_positive_int


# ---------------------------------------------------------------------------------------------
# policies
class Policy:
    """A controller: ``reset`` at every throw, then one ``act`` per frame.

    Subclasses set ``name`` and implement ``act``; ``privileged`` ones (the oracle) get the true
    throw in ``reset``. ``predicted`` is the latest predicted crossing ``(t, y)`` (or None) and
    ``forecasts`` records ``(t_now, times (H,), mean (H, 2), std (H, 2))`` when ``record`` is
    set, for figures.
    """

    name = "policy"
    privileged = False
    note = ""

    def reset(self, scene: Scene, rng: np.random.Generator, throw: Throw | None = None) -> None:
        """Start a throw: forget everything (the paper resets the model at every throw)."""
        self.scene = scene
        self.rng = rng
        self.target = scene.effector_start
        self.predicted = None
        self.forecasts = []
        self.record = False
        self.n_skipped = 0  # steps where the model declined to forecast (target kept)

    def act(self, frame: np.ndarray, k: int) -> float:
        """Frame ``k`` (H, W) seen at ``t = k dt``; returns the effector's target height, m."""
        raise NotImplementedError

    def _log(self, t_now, times, mean, std):
        if self.record:
            self.forecasts.append((float(t_now), np.asarray(times, float).copy(),
                                   np.asarray(mean, float).copy(), np.asarray(std, float).copy()))


class Oracle(Policy):
    """Knows the true trajectory: aims at the true crossing from the first frame."""

    name = "oracle"
    privileged = True

    def reset(self, scene, rng, throw=None):
        super().reset(scene, rng, throw)
        if throw is None:
            raise ValueError("throw: the oracle needs the true throw")
        self.throw = throw
        self.predicted = (throw.t_cross, throw.y_cross)

    def act(self, frame, k):
        if k == 0:
            th = self.throw
            sel = slice(0, None, _FINE)
            self._log(0.0, th.times[sel], th.states[sel, :2], np.zeros_like(th.states[sel, :2]))
        return self.throw.y_cross


class RandomTargets(Policy):
    """A uniform random target in the effector's range every ``1 / rate`` seconds."""

    def __init__(self, rate_hz: float):
        self.rate_hz = float(rate_hz)
        self.name = f"random-{rate_hz:g}hz"

    def act(self, frame, k):
        every = max(1, int(round(1.0 / (self.rate_hz * self.scene.dt))))
        if k % every == 0:
            lo, hi = self.scene.effector_range
            self.target = float(self.rng.uniform(lo, hi))
        return self.target


class React(Policy):
    """Wait and react: the target is the height the ball is seen at now (no prediction)."""

    name = "react"

    def act(self, frame, k):
        from sysid_bench.core.tracking import track

        y = track(frame[None])[0, 1]
        if np.isfinite(y):
            self.target = float(y)
        return self.target


class _ForecastTarget(Policy):
    """Shared: turn a forecast into a target at the predicted crossing."""

    def _aim(self, t_now, pos_now, mean, std=None):
        sc = self.scene
        h = mean.shape[0]
        times = t_now + sc.dt * np.arange(1, h + 1)
        self._log(t_now, times, mean, np.zeros_like(mean) if std is None else std)
        hit = crossing_from_forecast(t_now, pos_now, times, mean, sc.x_catch, sc.t_min)
        if hit is not None:
            self.predicted = (hit[0], hit[1])
            lo, hi = sc.effector_range
            self.target = float(np.clip(hit[1], lo, hi))
        return self.target

    def _horizon(self, k):
        # forecast to t_max (at least a few frames: a crossing may be about to happen)
        return max(4, self.scene.n_frames - 1 - k)


class Identify(_ForecastTarget):
    """Any registered identifying method: re-identify on all frames so far, forecast, aim.

    Parameters
    ----------
    method : str
        Registry name (``methods.available()``).
    every : int
        Re-identify every this many frames (each call costs a whole identification).
    start : int
        First frame count to identify on.
    **options
        The method's hyperparameters (``methods.get(method, **options)``).
    """

    def __init__(self, method: str, every: int = 5, start: int = 4, **options):
        import methods

        self.name = method
        self.every = check_positive_int(every, "every")
        self.start = check_positive_int(start, "start")
        self.est = methods.get(method, **options)

    def reset(self, scene, rng, throw=None):
        super().reset(scene, rng, throw)
        self.frames = []
        self.last_skip = ""

    def act(self, frame, k):
        from sysid_bench.core.estimator import Observation
        from sysid_bench.core.tracking import track

        self.frames.append(frame)
        n = len(self.frames)
        first = max(self.start, getattr(self.est, "min_frames", 1))
        if n < first or (n - first) % self.every:
            return self.target
        t = k * self.scene.dt
        try:
            fc = self.est.forecast(Observation(frames=np.stack(self.frames), dt=self.scene.dt),
                                   self._horizon(k))
        except ValueError as exc:
            # the method refused this prefix (e.g. the ball seen in too few frames yet): keep
            # the target and try again at the next replan; counted in the row (skipped_steps)
            self.n_skipped += 1
            self.last_skip = f"{type(exc).__name__}: {exc}"
            return self.target
        return self._aim(t, track(frame[None])[0], fc.mean, fc.std)


class StreamPolicy(_ForecastTarget):
    """A method's online stream sees every frame; its forecast sets the target.

    For the methods that declare ``online`` (a recurrent stream) and ``forecasts``; their
    ``policies`` declaration names the policies and their hyperparameters (Vid2Param:
    ``vid2param`` and ``vid2param-physics``, the camera checkpoint forecasting in latent space or
    through the physics). Reads the stream through its contract only
    (:class:`sysid_bench.core.estimator.Stream`): ``position`` and ``forecast``.

    Parameters
    ----------
    method : str
        Registered method (``methods.get(method, **options)``).
    name : str, optional
        The policy's name in tables (default ``method``).
    every : int, optional
        Replan every this many frames (default 5: a forecast fits the state and rolls out the
        particles, tens of milliseconds; the pushes in between cost about one).
    start : int
        First frame count to forecast from.
    threads : int or None
        The method's thread count (into its declared ``threads_param``, if it has one).
    **options
        The method's hyperparameters.
    """

    def __init__(self, method: str, name: str | None = None, every: int | None = None,
                 start: int = 4, threads: int | None = 1, **options):
        import methods

        spec = methods.spec(method)
        if not (spec.online and spec.forecasts):
            raise ValueError(f"method: expected a method whose stream is online and forecasts, "
                             f"got {method!r}")
        self.name = name or method
        self.every_opt = None if every is None else check_positive_int(every, "every")
        self.start = check_positive_int(start, "start")
        if spec.threads_param is not None and spec.threads_param not in options:
            options[spec.threads_param] = threads
        self.est = methods.get(method, **options)
        self.stream = self.est.stream()

    def reset(self, scene, rng, throw=None):
        super().reset(scene, rng, throw)
        self.stream.reset()
        self.frames = []
        self.floor_gap = []
        self.every = self.every_opt or 5

    def act(self, frame, k):
        from sysid_bench.core.estimator import POSITION_NOW
        from sysid_bench.core.tracking import track

        self.stream.push(frame)
        self.frames.append(frame)
        # A model that infers the floor from the bounces gives heights above that floor; the
        # effector works in the camera's frame, where the floor sits at an unknown height. The
        # gap between the tracked ball (camera frame) and the stream's height is that floor.
        seen = track(frame[None])[0]
        if np.isfinite(seen).all():
            self.floor_gap.append(seen[1] - self.stream.position()[1])
        n = len(self.frames)
        if n < self.start or (n - self.start) % self.every:
            return self.target
        floor = float(np.median(self.floor_gap)) if self.floor_gap else 0.0
        fc = self.stream.forecast(self._horizon(k), floor=floor)
        # the forecast's fitted position now starts the path, so a crossing due before its
        # first step is still seen (as the Identify policies do); the fit, not the stream's
        # raw position, since a camera model misreads the odd dropped frame by a metre
        now = fc.extras.get(POSITION_NOW)
        return self._aim(k * self.scene.dt, now, fc.mean, fc.std)

