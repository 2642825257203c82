"""The interception scene: the camera, the effector, the scoring rule and the throws (see the
package docstring)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from sysid_bench.core import physics
from sysid_bench.core._validate import check_number

#: The camera-like nuisances of the shipped ``camera`` checkpoint (its training record).
CAMERA_NUISANCE = {"blur": 0.5, "occlusion": 0.05, "drop": 0.05, "noise": 8.0,
                   "floor_offset": 1.0}
#: Fine integration steps per frame for the ground truth the throw is scored on.
_FINE = 10
#: A target change smaller than this (m) is not a decision (decision_s).
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
        from sysid_bench.core.render import check_size

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
    from sysid_bench.core.datasets import SUBRANGES_TEST
    from sysid_bench.core.render import render

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


