"""The interception task: the paper's robot experiment, simulated and closed on forecasts.

A slow end effector must meet a bouncing ball whose physics it does not know, from a camera-like
video seen one frame at a time, with its model reset at every throw (paper, last experiment: a
PR2 caught 27 of 35 throws; random policies at 1 Hz and 2 Hz caught 8 and 10).

The scene (:class:`Scene`, every number an option of :func:`evaluate`)
-----------------------------------------------------------------------
* Each throw draws ``e, g, d, r`` from the test split's sub-ranges (``datasets.SUBRANGES_TEST``),
  a launch from ``physics.STATE0_RANGES`` and a floor height ``U(0, floor_offset)`` (1 m); the
  ball is simulated on that floor and filmed by the fixed camera framed on floor 0 (so one world
  frame serves ball, camera and effector), 100x50 (W x H) with the camera-like nuisances of the
  shipped Vid2Param ``camera`` checkpoint: motion blur 0.5, occlusion 0.05, dropped frames 0.05,
  pixel noise 8 grey levels.
* The effector moves only vertically on the line ``x = x_catch = 5 m``, within
  ``[0, 11] m`` (the box over the highest floor), starting at 3.5 m, at most ``speed = 1 m/s``.
* The throw is scored at the first crossing of ``x_catch`` by the ball's centre after
  ``t_min = 3 s``: it succeeds when the effector is within ``catch_radius = 0.5 m`` of the
  ball's centre then. Every launch of the ranges reaches the floor before 2.3 s, so the scored
  crossing always comes after at least one bounce (``n_bounces`` records it). Throws are
  redrawn when the ball does not cross in ``(t_min, t_max = 8 s]`` (it stopped short of the
  line) or moved less than ``min_swing = 1 m`` up and down in the second before the crossing
  (rolling or hopping low: nothing left to predict).
* Why the limit bites: by ``t_min`` the effector covers 3 m from its start, ``[0.5, 6.5] m``
  (``[0, 7] m`` with the catch radius), and one more metre per second after, while crossing
  heights are 0.04-6.8 m (200 throws, seed 0): the crossings are reachable by an effector that
  knows them at launch (``reachable``; the oracle catches them), but the ball moves vertically at
  up to ~13 m/s, so a controller that waits and follows what it sees (the ``react`` policy)
  arrives too late. Without the limit ``react`` catches nearly every throw: it is the limit,
  not the camera, that makes prediction necessary (figures in ``docs/intercept.md``).

The controller sees frame ``k`` at ``t = k dt`` (20 Hz), returns a target height, and the effector
heads for it at the speed limit until the next frame (no actuation delay; the control step's
wall time is measured and reported separately).

Policies (:func:`make_policy`)
------------------------------
``oracle``         knows the true crossing: the ceiling.
``random-1hz``, ``random-2hz``  a uniform random target in the effector's range every 1 s / 0.5 s.
``react``          "wait and react": the target is the height the ball is seen at now.
``kalman``         tracked positions, a constant-acceleration Kalman filter per axis with bounce
                   and wall detection, ballistic prediction with bounce reflection (the suite's
                   simulator with the filter's gravity, restitution and floor, no drag).
declared policies   an online method's stream (:class:`StreamPolicy`), as the method declares
                   them (``policies``): Vid2Param's ``vid2param`` and ``vid2param-physics``,
                   its camera checkpoint forecasting in latent space or through the physics.
any registered identifying method (``lsq``, ``nuts``, ...)  re-identifies on all frames so far
                   every ``every`` frames and forecasts with its ``forecast``.

Forecasting policies aim at the forecast mean's first crossing of ``x_catch`` after ``t_min``.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from sysid_bench import physics
from sysid_bench._io import atomic_write
from sysid_bench._validate import (
    SEED_MAX,
    arg_number,
    check_flag,
    check_int_array,
    check_number,
    check_positive_int,
)

__all__ = [
    "Scene",
    "Throw",
    "Policy",
    "POLICIES",
    "known_policies",
    "make_policy",
    "make_throw",
    "evaluate",
    "summarise",
    "wilson_interval",
    "crossing_from_forecast",
    "report_section",
    "write_results",
    "intercept_figure",
    "CAMERA_NUISANCE",
    "add_arguments",
    "run",
]

#: The camera-like nuisances of the shipped ``camera`` checkpoint (its training record).
CAMERA_NUISANCE = {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0,
                   "floor_offset": 1.0}
#: Fine integration steps per frame for the ground truth the throw is scored on.
_FINE = 10
#: A target change smaller than this (m) is not a decision (decision_s).
_DECISION_TOL = 0.01


# ---------------------------------------------------------------------------------------------
# the scene
#: Largest catch radius, m: half the box's height. Beyond it an effector that never moves from
#: mid-height catches every ball, and a success rate says nothing about the policy.
CATCH_RADIUS_MAX = physics.BOX_WIDTH / 2


@dataclass(frozen=True)
class Scene:
    """The task's fixed geometry and rules (all public to the controller).

    Parameters
    ----------
    x_catch : float
        The effector's vertical line, metres, in (0, 10).
    catch_radius : float
        Largest effector-to-ball-centre distance at the crossing that counts as a catch, m, in
        ``(0, CATCH_RADIUS_MAX]``.
    speed : float
        The effector's speed limit, m/s, in ``(0, physics.V_MAX]``, or ``inf``: no limit (an
        analysis option of the API; the command line takes finite speeds only).
    t_min : float
        The scored crossing is the first after this flight time, s.
    t_max : float
        Throws with no crossing in ``(t_min, t_max]`` are redrawn, s.
    min_swing : float
        Throws whose ball moved less than this up and down in the second before the crossing
        (rolling, or hopping low: nothing left to predict) are redrawn, m; 0 keeps every throw.
    effector_range : (float, float)
        Heights the effector can reach, m; targets are clipped to it.
    effector_start : float
        Height at launch, m.
    dt : float
        Seconds between frames.
    size : (int, int)
        (H, W) of the frames.
    nuisance : dict
        ``render`` nuisances plus ``floor_offset`` (per-throw floor height ``U(0, floor_offset)``).
    """

    x_catch: float = 5.0
    catch_radius: float = 0.5
    speed: float = 1.0
    t_min: float = 3.0
    t_max: float = 8.0
    min_swing: float = 1.0
    effector_range: tuple = (0.0, 11.0)
    effector_start: float = 3.5
    dt: float = physics.DT
    size: tuple = (50, 100)
    nuisance: dict = field(default_factory=lambda: dict(CAMERA_NUISANCE))

    def __post_init__(self):
        def num(name, lo=-math.inf, hi=math.inf, inf_ok=False):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name}: expected a number, got {v!r}")
            v = float(v)
            if math.isnan(v) or (math.isinf(v) and not inf_ok) or not (lo < v < hi or
                                                                       (inf_ok and v == math.inf)):
                raise ValueError(f"{name}: expected a number in ({lo:g}, {hi:g}), got {v!r}")
            object.__setattr__(self, name, v)

        # beyond half the box's height an effector parked mid-way catches every ball
        num("catch_radius", 0.0, CATCH_RADIUS_MAX + 1e-12)
        # faster than any ball may start (physics.V_MAX) is "no limit": say so with inf
        num("speed", 0.0, physics.V_MAX + 1e-12, inf_ok=True)
        num("x_catch", 0.0, physics.BOX_WIDTH)
        num("dt", 0.0)
        num("t_min", 0.0)
        num("t_max", self.t_min)
        object.__setattr__(self, "min_swing", check_number(self.min_swing, "min_swing", lo=0.0))
        try:
            lo, hi = (float(v) for v in self.effector_range)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"effector_range: expected (low, high) in metres, got "
                             f"{self.effector_range!r}") from exc
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"effector_range: expected finite low < high, got {self.effector_range!r}")
        object.__setattr__(self, "effector_range", (lo, hi))
        num("effector_start", lo - 1e-12, hi + 1e-12)
        from sysid_bench.render import check_size

        object.__setattr__(self, "size", check_size(tuple(self.size)))
        if not isinstance(self.nuisance, dict):
            raise ValueError(f"nuisance: expected a dict, got {type(self.nuisance).__name__}")

    @property
    def n_frames(self) -> int:
        """Frames from launch to ``t_max``, launch included."""
        return int(math.floor(self.t_max / self.dt + 1e-9)) + 1

    def as_dict(self) -> dict:
        d = asdict(self)
        d["effector_range"] = list(d["effector_range"])
        d["size"] = list(d["size"])
        return d


_SCENE_FIELDS = {f.name for f in fields(Scene)}


@dataclass
class Throw:
    """One throw: what the world does (the controller sees only ``frames``).

    Attributes
    ----------
    index : int
    theta : ndarray, shape (4,)
        ``e, g, d, r``.
    state0 : ndarray, shape (4,)
    floor : float
        Floor height, world metres.
    times : ndarray, shape (F,)
        Fine time grid (``dt / 10``) up to ``t_max``.
    states : ndarray, shape (F, 4)
        True states on ``times``.
    frames : ndarray, shape (K, H, W), uint8
        Frames the controller sees: ``t = k dt`` for ``k < K``, every frame up to the crossing.
    t_cross, y_cross : float
        The scored crossing: time (s) and the ball centre's height (m).
    n_bounces : int
        Floor bounces before the crossing (>= 1 by construction of ``t_min``, checked).
    attempts : int
        Draws needed (redraws when no crossing fell in the window).
    """

    index: int
    theta: np.ndarray
    state0: np.ndarray
    floor: float
    times: np.ndarray
    states: np.ndarray
    frames: np.ndarray
    t_cross: float
    y_cross: float
    n_bounces: int
    attempts: int

    def reachable(self, scene: Scene) -> bool:
        """Whether an effector that knew the crossing at launch could be there in time."""
        return abs(self.y_cross - scene.effector_start) <= scene.speed * self.t_cross + scene.catch_radius


def _first_crossing(times, x, x_catch, t_min):
    """Index ``j`` and fraction ``f`` of the first crossing of ``x_catch`` after ``t_min``."""
    s = x - x_catch
    sign = np.sign(s)
    # a crossing inside [j, j+1]: sign changes or the next sample sits exactly on the line
    idx = np.flatnonzero((sign[:-1] * sign[1:] < 0) | ((sign[1:] == 0) & (sign[:-1] != 0)))
    for j in idx:
        f = s[j] / (s[j] - s[j + 1])
        t = times[j] + f * (times[j + 1] - times[j])
        if t >= t_min:
            return int(j), float(f), float(t)
    return None


def make_throw(scene: Scene, seed: int, index: int, max_attempts: int = 100) -> Throw:
    """Throw ``index`` of the evaluation seeded by ``seed`` (independent of the other throws).

    Draw ``j`` uses ``SeedSequence(seed, spawn_key=(index, j))`` (parameters, launch, floor,
    then the camera's nuisances); draws are repeated until the ball crosses ``x_catch`` in
    ``(t_min, t_max]`` having moved at least ``min_swing`` up and down in the second before.

    Raises
    ------
    RuntimeError
        No acceptable draw in ``max_attempts`` (a scene whose rules almost no throw meets).
    """
    from sysid_bench.datasets import SUBRANGES_TEST
    from sysid_bench.render import render

    n_fine = (scene.n_frames - 1) * _FINE + 1
    for j in range(max_attempts):
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(index), j)))
        theta = physics.sample_theta(1, rng, SUBRANGES_TEST)
        fo = float(scene.nuisance.get("floor_offset", 0.0))
        floor = float(rng.uniform(0.0, fo)) if fo > 0 else 0.0
        s0 = physics.sample_state0(1, rng, floor=floor)
        st = physics.simulate(theta, s0, n_frames=n_fine, dt=scene.dt / _FINE, floor=floor)[0]
        times = np.arange(n_fine) * (scene.dt / _FINE)
        hit = _first_crossing(times, st[:, 0], scene.x_catch, scene.t_min)
        if hit is None:
            continue
        k, f, t_cross = hit
        y_cross = float(st[k, 1] + f * (st[k + 1, 1] - st[k, 1]))
        last = st[max(0, k - int(round(1.0 / (scene.dt / _FINE)))) : k + 2, 1]
        if last.max() - last.min() < scene.min_swing:
            continue
        # bounces: vy turns from down to up at the floor before the crossing
        vy = st[: k + 2, 3]
        low = st[: k + 2, 1] - floor < 0.5
        n_bounces = int(np.sum((vy[:-1] < 0) & (vy[1:] >= 0) & low[1:]))
        n_seen = int(math.floor(t_cross / scene.dt + 1e-9)) + 1
        nuis = {k_: v for k_, v in scene.nuisance.items() if k_ != "floor_offset"}
        # the camera is fixed, framed on floor 0: a raised floor shows as a lifted ball
        frames = render(st[None, : (n_seen - 1) * _FINE + 1 : _FINE], scene.size, floor=0.0,
                        seed=[rng], dt=scene.dt, **nuis)[0]
        return Throw(index=int(index), theta=theta[0], state0=s0[0], floor=floor, times=times,
                     states=st, frames=frames, t_cross=t_cross, y_cross=y_cross,
                     n_bounces=n_bounces, attempts=j + 1)
    raise RuntimeError(f"throw {index}: no crossing of x_catch in ({scene.t_min}, {scene.t_max}] s "
                       f"in {max_attempts} draws (min_swing {scene.min_swing} m); widen t_max or lower min_swing")


# ---------------------------------------------------------------------------------------------
# crossing prediction shared by the forecasting policies
def crossing_from_forecast(t_now, pos_now, times, mean, x_catch, t_min):
    """First crossing of ``x_catch`` by a forecast mean after ``t_min``.

    Parameters
    ----------
    t_now : float
        Time of the last seen frame, s.
    pos_now : array_like, shape (2,) or None
        Position estimate at ``t_now`` (prepended to the path so a crossing in the first interval
        counts); ``None`` to use the forecast alone.
    times : ndarray, shape (H,)
        Times of the forecast steps, s.
    mean : ndarray, shape (H, 2)
        Forecast mean positions, metres.
    x_catch, t_min : float

    Returns
    -------
    (float, float, int) or None
        Crossing time, height, and the forecast step index at or after it; ``None`` when the
        forecast does not cross in its horizon.
    """
    times = np.asarray(times, dtype=float)
    mean = np.asarray(mean, dtype=float)
    off = 0
    if pos_now is not None and np.all(np.isfinite(pos_now)):
        times = np.concatenate([[t_now], times])
        mean = np.concatenate([np.asarray(pos_now, float)[None], mean])
        off = 1
    hit = _first_crossing(times, mean[:, 0], x_catch, t_min)
    if hit is None:
        return None
    j, f, t = hit
    y = float(mean[j, 1] + f * (mean[j + 1, 1] - mean[j, 1]))
    return t, y, max(0, j + 1 - off)


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
        from sysid_bench.tracking import track

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


class Kalman(_ForecastTarget):
    """Constant-acceleration Kalman filter per axis on tracked positions; ballistic prediction.

    Bounces are detected when a measurement lands well above the prediction of a falling ball
    (then the contact time is solved for with the current restitution estimate, the floor is
    read at it and the vertical velocity reflected); walls at x = 0 and 10 reflect the
    horizontal state. Restitution is re-estimated a few frames after each bounce. The forecast
    is the suite's simulator run from the filtered state with the filter's gravity, restitution
    and floor and no drag or rolling resistance.

    Parameters
    ----------
    sigma : float
        Tracking noise std, m.
    q : float
        White-jerk spectral density of the filter (m^2/s^5).
    e0 : float
        Restitution before any bounce was measured.
    floor0 : float or None
        Floor guess before the first bounce; None: half the scene's floor offset range.
    every : int
        Replan every this many frames.
    """

    name = "kalman"

    def __init__(self, sigma: float = 0.08, q: float = 2.0, e0: float = 0.8, floor0=None,
                 every: int = 1):
        self.sigma, self.q, self.e0, self.floor0 = float(sigma), float(q), float(e0), floor0
        self.every = check_positive_int(every, "every")

    def reset(self, scene, rng, throw=None):
        super().reset(scene, rng, throw)
        dt = scene.dt
        self.F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        q = self.q
        self.Q = q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                               [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                               [dt**3 / 6, dt**2 / 2, dt]])
        self.s = None  # (2, 3): x and y states [p, v, a]
        self.P = None  # (2, 3, 3)
        self.floor = (0.5 * float(scene.nuisance.get("floor_offset", 0.0))
                      if self.floor0 is None else float(self.floor0))
        self.floor_seen = False
        self.n_floor = 0
        self.e_est = []
        self.bounce = None  # (t_contact, v_before, frames since) awaiting an e estimate
        self.t_last = None

    def _init(self, z, t):
        g0 = -9.81
        self.s = np.array([[z[0], 0.0, 0.0], [z[1], 0.0, g0]])
        self.P = np.array([np.diag([self.sigma**2, 64.0, 0.5]), np.diag([self.sigma**2, 25.0, 4.0])])
        self.t_last = t

    @property
    def e(self):
        return float(np.clip(np.mean(self.e_est), 0.3, 1.0)) if self.e_est else self.e0

    def _update(self, i, z):
        H = np.array([1.0, 0.0, 0.0])
        S = self.P[i][0, 0] + self.sigma**2
        K = self.P[i][:, 0] / S
        self.s[i] = self.s[i] + K * (z - self.s[i][0])
        self.P[i] = self.P[i] - np.outer(K, H @ self.P[i])

    def act(self, frame, k):
        from sysid_bench.tracking import track

        sc = self.scene
        t = k * sc.dt
        self._t_prev = t - sc.dt
        z = track(frame[None])[0]
        seen = bool(np.all(np.isfinite(z)))
        if self.s is None:
            if not seen:
                return self.target
            self._init(z, t)
        else:
            prev = self.s.copy()
            for i in range(2):
                self.s[i] = self.F @ self.s[i]
                self.P[i] = self.F @ self.P[i] @ self.F.T + self.Q
            # walls: elastic and at known places (the camera is framed on the box)
            for wall, out in ((0.0, self.s[0, 0] < 0.0),
                              (physics.BOX_WIDTH, self.s[0, 0] > physics.BOX_WIDTH)):
                if out:
                    self.s[0, 0] = 2 * wall - self.s[0, 0]
                    self.s[0, 1] = -self.s[0, 1]
            bounced = False
            if seen:
                gate = max(0.3, 4.0 * math.sqrt(self.P[1][0, 0] + self.sigma**2))
                falling = prev[1, 1] < 0
                below = self.s[1, 0] < (self.floor if self.floor_seen else prev[1, 0])
                if falling and (z[1] - self.s[1, 0] > gate or (self.floor_seen and below)):
                    bounced = self._bounce(prev, z[1])
                if abs(z[0] - self.s[0, 0]) < 3.0:  # occlusion can shift a centroid: gate it
                    self._update(0, z[0])
                if bounced or abs(z[1] - self.s[1, 0]) < 3.0:
                    self._update(1, z[1])
            elif self.floor_seen and self.s[1, 0] < self.floor and prev[1, 1] < 0:
                self._bounce(prev, None)
            if self.bounce is not None and not bounced:
                tc, vb, n = self.bounce
                n += 1 if seen else 0
                if n >= 4:
                    va = self.s[1, 1] - self.s[1, 2] * (t - tc)
                    if vb < -0.5 and va > 0:
                        self.e_est.append(float(np.clip(va / -vb, 0.3, 1.0)))
                    self.bounce = None
                else:
                    self.bounce = (tc, vb, n)
            self.s[1, 2] = float(np.clip(self.s[1, 2], -13.5, -6.0))
        if k % self.every:
            return self.target
        return self._predict(t)

    def _bounce(self, prev, zy):
        """A floor contact between the previous frame and now: solve its time, reflect vy."""
        dt = self.scene.dt
        y0, v0, a = prev[1]
        e = self.e
        tau = np.linspace(0.0, dt, 41)
        fl = y0 + v0 * tau + a * tau**2 / 2
        vc = v0 + a * tau
        rest = dt - tau
        y1 = fl - e * vc * rest + a * rest**2 / 2
        if zy is None:
            j = int(np.argmin(np.abs(fl - self.floor)))
        else:
            j = int(np.argmin(np.abs(y1 - zy)))
        if vc[j] >= 0:
            return False
        if zy is not None:
            # floor estimates: running mean over bounces (the first replaces the guess)
            n = self.n_floor
            self.floor = (self.floor * n + fl[j]) / (n + 1)
            self.n_floor = n + 1
            self.floor_seen = True
        self.s[1, 0] = y1[j]
        self.s[1, 1] = -e * vc[j] + a * rest[j]
        self.P[1][1, 1] += 4.0  # the restitution is uncertain: so is the new velocity
        self.bounce = (self._t_prev + tau[j], float(vc[j]), 0)
        return True

    def _predict(self, t):
        sc = self.scene
        h = self._horizon(int(round(t / sc.dt)))
        x, vx = self.s[0, 0], self.s[0, 1]
        y, vy, ay = self.s[1, 0], self.s[1, 1], self.s[1, 2]
        floor = self.floor
        x = float(np.clip(x, 0.0, physics.BOX_WIDTH))
        y = float(np.clip(y, floor, floor + physics.BOX_WIDTH))
        theta = np.array([[self.e, ay, 0.0, 0.0]])
        st = physics.simulate(theta, np.array([[x, y, vx, vy]]), n_frames=h + 1, dt=sc.dt,
                              floor=floor)[0, 1:, :2]
        # the band: the filter's covariance carried forward by the constant-acceleration model
        # (bounces and walls ignored), J_k = [1, k dt, (k dt)^2 / 2]
        tk = sc.dt * np.arange(1, h + 1)
        J = np.stack([np.ones_like(tk), tk, tk**2 / 2], axis=1)
        std = np.sqrt(np.stack([np.einsum("hi,ij,hj->h", J, self.P[i], J) for i in range(2)], 1))
        return self._aim(t, (x, y), st, std)


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
        from sysid_bench.estimator import Observation
        from sysid_bench.tracking import track

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
    (:class:`sysid_bench.estimator.Stream`): ``position`` and ``forecast``.

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
        from sysid_bench.estimator import POSITION_NOW
        from sysid_bench.tracking import track

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


#: Built-in policy names -> factories (registered identifying methods are added by name).
POLICIES = {
    "oracle": lambda **o: Oracle(**o),
    "random-1hz": lambda **o: RandomTargets(1.0, **o),
    "random-2hz": lambda **o: RandomTargets(2.0, **o),
    "react": lambda **o: React(**o),
    "kalman": lambda **o: Kalman(**o),
}


def _stream_policies() -> dict[str, tuple[str, dict]]:
    """``{policy: (method, hyperparameters)}`` declared by the registered methods (``policies``:
    online methods that forecast). Reads every method's declarations (imports its module)."""
    import methods

    out: dict[str, tuple[str, dict]] = {}
    for m in methods.available():
        try:
            sp = methods.spec(m)
        except ImportError:  # a method whose packages are not installed offers no policy
            continue
        for pol, opts in sp.policies.items():
            out.setdefault(pol, (m, dict(opts)))
    return out


def _is_policy(name) -> bool:
    """A built-in policy, one declared by an online method, or a registered method that
    forecasts (its forecast sets the target)."""
    import methods

    if not isinstance(name, str):
        return False
    if name in POLICIES or name in _stream_policies():
        return True
    return name in methods.available() and methods.spec(name).forecasts


def known_policies() -> list[str]:
    """Every policy name :func:`make_policy` accepts (imports every registered method)."""
    import methods

    declared = list(_stream_policies())
    return list(POLICIES) + declared + [m for m in methods.available()
                                        if m not in POLICIES and m not in declared
                                        and _is_policy(m)]


def make_policy(name: str, **options) -> Policy:
    """A policy by name; ``options`` go to its constructor.

    Raises
    ------
    ValueError
        Unknown name (the message lists the known ones) or options the policy does not take.
    """
    if not _is_policy(name):
        known = ", ".join(known_policies())
        raise ValueError(f"policy: unknown policy {name!r}; known policies: {known}")
    try:
        if name in POLICIES:
            return POLICIES[name](**options)
        declared = _stream_policies()
        if name in declared:
            method, base = declared[name]
            return StreamPolicy(method, name=name, **{**base, **options})
        return Identify(name, **options)
    except TypeError as exc:
        raise ValueError(f"options: policy {name!r} does not take {sorted(options)} ({exc})") from exc


# ---------------------------------------------------------------------------------------------
# evaluation
def wilson_interval(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``k / n`` (95% by default).

    ``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")`` at the confidence level of
    the two-sided normal quantile ``z``. ``n = 0`` gives ``(nan, nan)``.
    """
    from scipy import stats

    if n <= 0:
        return (float("nan"), float("nan"))
    if not 0 <= k <= n:
        raise ValueError(f"k: expected a count in [0, n={n}], got {k}")
    if not z > 0:
        raise ValueError(f"z: expected a positive normal quantile, got {z!r}")
    level = 1.0 - 2.0 * stats.norm.sf(z)
    ci = stats.binomtest(int(k), int(n)).proportion_ci(confidence_level=level, method="wilson")
    return (float(ci.low), float(ci.high))


def _effector(p, target, span, speed):
    """Height after heading for ``target`` for ``span`` seconds at ``speed``."""
    if math.isinf(speed):
        return target
    step = speed * span
    return p + min(max(target - p, -step), step)


def _run_throw(policy: Policy, scene: Scene, throw: Throw, rng, record: bool):
    """Close the loop on one throw; returns (row dict, trace dict or None)."""
    policy.reset(scene, rng, throw if policy.privileged else None)
    policy.record = record
    lo, hi = scene.effector_range
    p = scene.effector_start
    prev_target = p
    decision = 0.0
    steps, path_t, path_y, targets = [], [0.0], [p], []
    err = ""
    n = throw.frames.shape[0]
    for k in range(n):
        t = k * scene.dt
        t0 = time.perf_counter()
        try:
            target = float(policy.act(throw.frames[k], k))
            if not math.isfinite(target):
                raise ValueError(f"target: expected a finite height, got {target!r}")
        except Exception as exc:  # noqa: BLE001 -- a failing policy fails its throw, not the run
            err = f"{type(exc).__name__}: {exc}"
            break
        steps.append(time.perf_counter() - t0)
        target = min(max(target, lo), hi)
        if abs(target - prev_target) > _DECISION_TOL:
            decision = t
        prev_target = target
        targets.append(target)
        t_next = min((k + 1) * scene.dt, throw.t_cross)
        p = _effector(p, target, t_next - t, scene.speed)
        path_t.append(t_next)
        path_y.append(p)
    miss = abs(p - throw.y_cross) if not err else float("nan")
    # the earliest frame from which every target stayed within the catch radius of the truth
    ok = np.abs(np.asarray(targets) - throw.y_cross) <= scene.catch_radius
    settled = float("nan")
    if not err and len(ok) and ok[-1]:
        settled = float(len(ok) - np.argmin(ok[::-1]) if not ok.all() else 0) * scene.dt
    pred = policy.predicted or (float("nan"), float("nan"))
    th = throw.theta
    row = {
        "throw": throw.index,
        "success": bool(not err and miss <= scene.catch_radius),
        "miss_m": miss,
        "decision_s": decision,
        "settled_s": settled,
        "step_ms": 1e3 * float(np.median(steps)) if steps else float("nan"),
        "step_mean_ms": 1e3 * float(np.mean(steps)) if steps else float("nan"),
        "skipped_steps": int(getattr(policy, "n_skipped", 0)),
        "t_cross_s": throw.t_cross,
        "y_cross_m": throw.y_cross,
        "effector_m": p if not err else float("nan"),
        "pred_t_cross_s": float(pred[0]),
        "pred_y_cross_m": float(pred[1]),
        "reachable": throw.reachable(scene),
        "n_bounces": throw.n_bounces,
        "n_frames": n,
        "floor_m": throw.floor,
        "e": th[0], "g": th[1], "d": th[2], "r": th[3],
        "error": err,
    }
    trace = None
    if record:
        end = int(np.searchsorted(throw.times, throw.t_cross)) + 1
        trace = {
            "throw": throw.index, "policy": policy.name, "success": row["success"],
            "ball_t": throw.times[:end].tolist(), "ball_x": throw.states[:end, 0].tolist(),
            "ball_y": throw.states[:end, 1].tolist(), "t_cross": throw.t_cross,
            "y_cross": throw.y_cross, "floor": throw.floor,
            "effector_t": path_t, "effector_y": path_y, "targets": targets,
            "forecasts": [{"t": f[0], "times": f[1].tolist(), "mean": f[2].tolist(),
                           "std": f[3].tolist()} for f in policy.forecasts],
        }
    return row, trace


def evaluate(policy, n_throws: int = 200, seed: int = 0, **options):
    """Success of a policy over seeded throws.

    Parameters
    ----------
    policy : str or Policy
        A name of :func:`known_policies` or a :class:`Policy` instance.
    n_throws : int
        Throws (>= 1). Throw ``i`` depends only on ``(seed, i)``.
    seed : int
    **options
        :class:`Scene` fields (``x_catch``, ``catch_radius``, ``speed``, ``t_min``, ``t_max``,
        ``effector_range``, ``effector_start``, ``dt``, ``size``, ``nuisance``); ``progress``
        (tqdm bar, default False); ``record`` (throw indices whose traces -- ball path, forecasts,
        effector -- go to ``df.attrs["traces"]``); the rest go to the policy's constructor.

    Returns
    -------
    pandas.DataFrame
        One row per throw: ``throw``, ``success`` (bool), ``miss_m`` (|effector - ball| at the
        crossing, m; NaN when the policy raised), ``decision_s`` (time of the last target change
        of more than 1 cm), ``step_ms`` (the policy's median control-step time over the throw),
        ``settled_s`` (the earliest frame time from which every target stayed within the catch
        radius of the true crossing height; NaN if the last one did not),
        ``step_mean_ms`` (its mean: replanning every few frames puts the cost in the mean),
        ``skipped_steps`` (replans where the model declined this prefix, e.g. too few frames
        with the ball seen; the target was kept),
        ``t_cross_s``, ``y_cross_m`` (the true crossing), ``effector_m``, ``pred_t_cross_s``,
        ``pred_y_cross_m`` (the policy's last predicted crossing, NaN if none), ``reachable``
        (an effector knowing the crossing at launch could make it), ``n_bounces``, ``n_frames``
        (frames seen), ``floor_m``, ``e``, ``g``, ``d``, ``r``, ``error`` (why the policy
        raised, empty if it did not). ``attrs``: ``policy``, ``note``, ``seed``, ``scene``,
        ``traces``.
    """
    import pandas as pd

    if isinstance(n_throws, bool) or not isinstance(n_throws, (int, np.integer)) or n_throws < 1:
        raise ValueError(f"n_throws: expected an int >= 1, got {n_throws!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
    progress = check_flag(options.pop("progress", False), "progress")
    record = list(options.pop("record", ()))
    # a throw index that is not thrown would keep no trace without a word
    record = (set() if not record else
              {int(i) for i in check_int_array(record, "record", lo=0, hi=int(n_throws) - 1)})
    scene = Scene(**{k: options.pop(k) for k in list(options) if k in _SCENE_FIELDS})
    if isinstance(policy, Policy):
        if options:
            raise ValueError(f"options: {sorted(options)} are neither Scene fields nor usable "
                             "with a Policy instance")
        pol = policy
    else:
        pol = make_policy(policy, **options)
    it = range(int(n_throws))
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=f"intercept {pol.name}", unit="throw")
    rows, traces = [], {}
    for i in it:
        throw = make_throw(scene, seed, i)
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(i), 1 << 20)))
        row, trace = _run_throw(pol, scene, throw, rng, i in record)
        rows.append(row)
        if trace is not None:
            traces[i] = trace
    df = pd.DataFrame(rows)
    df.attrs.update(policy=pol.name, note=pol.note, seed=int(seed), scene=scene.as_dict(),
                    traces=traces)
    return df


def summarise(df) -> dict:
    """Rates of an :func:`evaluate` table: throws, caught, rate and its 95% Wilson CI, ...."""
    n = int(len(df))
    k = int(df.success.sum())
    lo, hi = wilson_interval(k, n)
    ok = df[df.error == ""]
    return {
        "policy": df.attrs.get("policy", ""),
        "throws": n,
        "caught": k,
        "rate": k / n if n else float("nan"),
        "ci95_lo": lo,
        "ci95_hi": hi,
        "median_miss_m": float(ok.miss_m.median()) if len(ok) else float("nan"),
        "median_lead_s": float((ok.t_cross_s - ok.decision_s).median()) if len(ok) else float("nan"),
        # how long before the crossing the aim was right for good (0 where it never was)
        "median_settled_lead_s": float((ok.t_cross_s - ok.settled_s).fillna(0.0).median())
        if len(ok) else float("nan"),
        "median_step_ms": float(df.step_ms.median()),
        "mean_step_ms": float(df.step_mean_ms.mean()),
        "errors": int((df.error != "").sum()),
        "seed": df.attrs.get("seed"),
        "note": df.attrs.get("note", ""),
    }


# ---------------------------------------------------------------------------------------------
# files, the report section, the command line


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def thin_trace(trace: dict, n_forecasts: int = 12) -> dict:
    """A throw's trace made small for disk: at most ``n_forecasts`` forecasts, evenly spread
    (first and last kept), numbers rounded to 1 mm / 1 ms."""

    def rnd(v):
        if isinstance(v, float):
            return round(v, 3)
        if isinstance(v, list):
            return [rnd(x) for x in v]
        if isinstance(v, dict):
            return {k: rnd(x) for k, x in v.items()}
        return v

    out = dict(trace)
    fcs = trace.get("forecasts", [])
    if len(fcs) > n_forecasts:
        keep = np.unique(np.linspace(0, len(fcs) - 1, n_forecasts).round().astype(int))
        out["forecasts"] = [fcs[i] for i in keep]
    return rnd(out)


def write_results(df, out_dir, command: str = "", extra: dict | None = None) -> tuple[Path, Path]:
    """Write an :func:`evaluate` table and its summary (with the scene and traces).

    Files: ``out_dir/tables/intercept_<policy>.csv`` (one row per throw) and
    ``out_dir/tables/intercept_<policy>.json`` (summary, scene, seed, command, traces and the
    keys of ``extra``), both written atomically. Returns their paths.
    """
    tab = Path(out_dir) / "tables"
    base = tab / f"intercept_{_slug(df.attrs.get('policy', 'policy'))}"
    csv, js = base.with_suffix(".csv"), base.with_suffix(".json")
    atomic_write(csv, df.to_csv(index=False))
    meta = {"summary": summarise(df), "scene": df.attrs.get("scene"), "command": command,
            "traces": {str(k): thin_trace(v) for k, v in df.attrs.get("traces", {}).items()},
            **(extra or {})}
    atomic_write(js, json.dumps(meta, default=float))
    return csv, js


#: Order of the built-in policies in tables and figures, after those of the methods.
_BUILTIN_ORDER = ("kalman", "react", "random-2hz", "random-1hz", "oracle")


def _order_key(policy: str) -> tuple:
    """Tables and figures list the methods' policies first, in registry order (names only:
    nothing is imported), then other declared policies by name, then the built-ins; a drawn
    throw prefers the first with a trace."""
    import methods

    reg = methods.available(include_reference=True)
    if policy in reg:
        return (0, reg.index(policy), policy)
    if policy in _BUILTIN_ORDER:
        return (2, _BUILTIN_ORDER.index(policy), policy)
    return (1, 0, policy)


def _load_results(out_dir):
    tab = Path(out_dir) / "tables"
    res = {}
    for js in sorted(tab.glob("intercept_*.json")):
        try:
            meta = json.loads(js.read_text())
        except (OSError, ValueError):
            continue
        if "summary" in meta:
            res[meta["summary"]["policy"]] = meta
    return dict(sorted(res.items(), key=lambda kv: _order_key(kv[0])))


def intercept_figure(results: dict, path, draw: str | None = None) -> Path | None:
    """Success rates with 95% CIs per policy, and one throw drawn (height and x against time).

    Parameters
    ----------
    results : dict
        policy -> the JSON written by :func:`write_results`.
    path : path of the PNG.
    draw : str, optional
        Policy whose recorded throw to draw; default the first in table order with a trace.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sysid_bench.bench.figures import save_figure

    if not results:
        return None
    pols = list(results)
    rates = np.array([results[p]["summary"]["rate"] for p in pols])
    lo = np.array([results[p]["summary"]["ci95_lo"] for p in pols])
    hi = np.array([results[p]["summary"]["ci95_hi"] for p in pols])
    if draw is None:
        draw = next((p for p in pols if p != "oracle" and results[p].get("traces")), None)
    trace = None
    if draw is not None and results.get(draw, {}).get("traces"):
        trace = next(iter(results[draw]["traces"].values()))
    ncol = 3 if trace else 1
    fig, axes = plt.subplots(1, ncol, figsize=(5.0 * ncol, 3.8), squeeze=False)
    ax = axes[0, 0]
    y = np.arange(len(pols))
    ax.barh(y, 100 * rates, color="#4c72b0", alpha=0.8)
    ax.errorbar(100 * rates, y, xerr=[100 * (rates - lo), 100 * (hi - rates)], fmt="none",
                ecolor="k", capsize=3)
    ax.set_yticks(y, [f"{p} (n={results[p]['summary']['throws']})" for p in pols])
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("throws caught, % (95% Wilson CI)")
    ax.axvline(77, color="grey", ls=":", lw=1, label="paper's PR2 (27/35)")
    ax.legend(fontsize=7, loc="lower right")
    if trace:
        sc = results[draw].get("scene") or {}
        bt, bx, by = (np.asarray(trace[k]) for k in ("ball_t", "ball_x", "ball_y"))
        fcs = trace["forecasts"]
        pick = [fcs[i] for i in sorted({int(round(q * (len(fcs) - 1))) for q in (0.0, 0.4, 0.8)})] \
            if fcs else []
        colours = ["#dd8452", "#55a868", "#8172b3"]
        for ax, dim, b in ((axes[0, 1], 1, by), (axes[0, 2], 0, bx)):
            ax.plot(bt, b, color="k", lw=1.5, label="ball (true)")
            for c, f in zip(colours, pick):
                ft, fm, fs = np.asarray(f["times"]), np.asarray(f["mean"]), np.asarray(f["std"])
                ax.plot(ft, fm[:, dim], color=c, lw=1, label=f"forecast at {f['t']:.2f} s")
                ax.fill_between(ft, fm[:, dim] - 2 * fs[:, dim], fm[:, dim] + 2 * fs[:, dim],
                                color=c, alpha=0.2)
            ax.axvline(trace["t_cross"], color="grey", ls="--", lw=1)
            ax.set_xlim(0, trace["t_cross"] + 0.5)
            ax.set_xlabel("t (s)")
        ax = axes[0, 1]
        ax.plot(trace["effector_t"], trace["effector_y"], color="#c44e52", lw=2, label="effector")
        r = sc.get("catch_radius", 0.5)
        ax.errorbar([trace["t_cross"]], [trace["y_cross"]], yerr=[[r], [r]], fmt="o", color="k",
                    capsize=4, ms=4, label="catch window")
        ax.set_ylabel("height y (m)")
        ax.set_title(f"{draw}, throw {trace['throw']}: "
                     f"{'caught' if trace['success'] else 'missed'}", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
        ax = axes[0, 2]
        ax.axhline(sc.get("x_catch", 5.0), color="#c44e52", lw=1.5, label="x_catch")
        ax.set_ylabel("x (m)")
        ax.set_title("across: when the ball reaches the line (bands: mean +- 2 std)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, path)


def report_section(out_dir, source=None) -> list[str]:
    """Markdown of the interception section from the tables a run measured.

    Reads ``source/tables/intercept_*.json`` (default ``out_dir``: the run directory's, where
    ``sysid_bench.report.measure_intercept`` writes them); writes
    ``out_dir/tables/intercept_summary.csv``, a copy of each policy's per-throw CSV and
    ``out_dir/figures/intercept.png``. Computes nothing.
    """
    import pandas as pd

    out = Path(out_dir)
    src = out if source is None else Path(source)
    md = ["## 8. Interception (the paper's robot experiment, simulated)", ""]
    res = _load_results(src)
    if not res:
        return md + ["_No interception tables in this run (`sysid-bench report` measures them "
                     "into the run directory after the grid)._", ""]
    if src.resolve() != out.resolve():
        for p in res:
            csv = src / "tables" / f"intercept_{_slug(p)}.csv"
            if csv.is_file():
                atomic_write(out / "tables" / csv.name, csv.read_bytes())
    sc = next(iter(res.values())).get("scene") or {}
    md += [f"A ball drawn from the test sub-ranges, filmed at 20 Hz with camera nuisances "
           f"({', '.join(f'{k} {v:g}' for k, v in sorted((sc.get('nuisance') or {}).items()))}), "
           f"must be met by an effector moving only vertically on x = {sc.get('x_catch'):g} m at "
           f"most {sc.get('speed'):g} m/s from {sc.get('effector_start'):g} m, within "
           f"{sc.get('catch_radius'):g} m of the ball's centre at its first crossing after "
           f"{sc.get('t_min'):g} s (always after a bounce). Models are reset at every throw. "
           "Rates with 95% Wilson intervals; the paper's PR2 caught 27/35 (77%), its random "
           "policies 8/35 and 10/35. See `docs/intercept.md` and `sysid_bench/intercept.py`.", ""]
    rows = []
    for p, meta in res.items():
        s = meta["summary"]
        rows.append({"policy": p, "throws": s["throws"], "caught": s["caught"],
                     "rate %": 100 * s["rate"],
                     "95% CI %": f"{100 * s['ci95_lo']:.1f}-{100 * s['ci95_hi']:.1f}",
                     "median miss m": s["median_miss_m"],
                     "median lead s": s["median_lead_s"],
                     "median settled lead s": s.get("median_settled_lead_s", float("nan")),
                     "median step ms": s["median_step_ms"],
                     "mean step ms": s.get("mean_step_ms", float("nan")), "errors": s["errors"],
                     "seed": s["seed"], "note": s.get("note", "")})
    t = pd.DataFrame(rows)
    atomic_write(out / "tables" / "intercept_summary.csv", t.to_csv(index=False))
    from sysid_bench._markdown import markdown_table

    md += ["**intercept_summary** (`tables/intercept_summary.csv`; per-throw rows in "
           "`tables/intercept_<policy>.csv`)", "", markdown_table(t, floatfmt=".3g"), ""]
    fig = intercept_figure(res, out / "figures" / "intercept.png")
    if fig is not None:
        cap = ("Interception: success rates with 95% CIs; one throw of the first forecasting "
               "policy drawn: the ball, its forecast (mean +- 2 std) at three instants, the "
               "effector and the catch window at the crossing")
        md += [f"![{cap}]({fig.relative_to(out).as_posix()})", "", f"*{cap}*", ""]
    return md


def _option_value(text: str):
    try:
        return json.loads(text)
    except ValueError:
        return text


def add_arguments(p):
    """The ``intercept`` options on a ``sysid-bench`` subcommand parser
    (``sysid_bench.cli.SUBCOMMANDS``)."""
    p.add_argument("--policy", required=True,
                   help="oracle, random-1hz, random-2hz, react, kalman, a policy an online "
                        "method declares, or a registered method that forecasts (lsq, ...)")
    p.add_argument("--throws", type=arg_number(1, 10**6, integer=True), default=200,
                   help="number of throws (default 200)")
    p.add_argument("--seed", type=arg_number(0, SEED_MAX, integer=True), default=0,
                   help="seed of the throws (default 0)")
    p.add_argument("--out", default="runs/intercept",
                   help="output directory (default runs/intercept/; the report's interception "
                        "tables are measured by the run itself)")
    p.add_argument("--speed", type=arg_number(0, physics.V_MAX, lo_open=True, unit="m/s"),
                   default=None, help=f"effector speed limit, m/s (0 < speed <= {physics.V_MAX:g})")
    p.add_argument("--catch-radius", type=arg_number(0, CATCH_RADIUS_MAX, lo_open=True, unit="m"),
                   default=None, help=f"catch radius, m (0 < r <= {CATCH_RADIUS_MAX:g})")
    p.add_argument("--draw", type=arg_number(0, None, integer=True), default=0,
                   help="throw whose trace is kept for the figure (0 to --throws - 1)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a scene field or policy option (JSON value), e.g. every=3; repeatable")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(fn=run)
    return p


def run(args) -> int:
    """``sysid-bench intercept``: evaluate, print the rates, write the table. Returns 0."""
    import shlex
    import sys

    opts = {}
    for kv in args.option:
        if "=" not in kv:
            raise ValueError(f"--option: expected KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        opts[k.strip().replace("-", "_")] = _option_value(v)
    if args.draw >= args.throws:
        raise ValueError(f"draw: expected a throw in [0, {args.throws - 1}] (--throws "
                         f"{args.throws}), got {args.draw}")
    if args.speed is not None:
        opts["speed"] = args.speed
    if args.catch_radius is not None:
        opts["catch_radius"] = args.catch_radius
    df = evaluate(args.policy, n_throws=args.throws, seed=args.seed, record=[args.draw],
                  progress=not args.no_progress, **opts)
    cmd = (f"sysid-bench intercept --policy {shlex.quote(args.policy)} --throws {args.throws} "
           f"--seed {args.seed} --draw {args.draw}"
           + (f" --speed {args.speed:g}" if args.speed is not None else "")
           + (f" --catch-radius {args.catch_radius:g}" if args.catch_radius is not None else "")
           + "".join(f" --option {shlex.quote(o)}" for o in args.option))
    csv, js = write_results(df, args.out, command=cmd)
    s = summarise(df)
    print(f"{s['policy']}: caught {s['caught']}/{s['throws']} = {100 * s['rate']:.1f}% "
          f"(95% CI {100 * s['ci95_lo']:.1f}-{100 * s['ci95_hi']:.1f}%), median miss "
          f"{s['median_miss_m']:.3f} m, control step median {s['median_step_ms']:.2f} ms "
          f"(mean {s['mean_step_ms']:.2f} ms), {s['errors']} errors")
    if s["note"]:
        print(f"note: {s['note']}")
    print(f"table: {csv}")
    if s["errors"]:
        first = df[df.error != ""].iloc[0]
        print(f"first error (throw {first.throw}): {first.error}", file=sys.stderr)
    return 0
