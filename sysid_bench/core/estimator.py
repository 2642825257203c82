"""The one interface every method sits behind, and the result types it returns.

``Observation`` is what a method sees (frames and/or positions), ``Posterior`` its answer about
the physical parameters, ``Forecast`` its answer about future positions. All three validate on
construction, so a malformed result fails where it is made, not three modules later in a metric.

Like scikit-learn estimators, a constructor only stores hyperparameters (keyword arguments, no
work, no validation beyond storing); state learned by ``fit`` ends in ``_``.
"""

from __future__ import annotations

import abc
import functools
import inspect
import math
import sys
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from sysid_bench.core._observation_checks import BOX_MARGIN, DT_RANGE
from sysid_bench.core._validate import (
    as_float_array,
    check_annotated,
    check_horizon,
    check_int,
    check_int_array,
    check_number,
    check_positive_int,
    check_seed,
    check_seed_value,
)
from sysid_bench.core.metrics import central_z
from sysid_bench.core.physics import (
    BOX_WIDTH,
    FLOOR_MAX,
)
from sysid_bench.core.spec import MethodSpec, spec_of

__all__ = [
    "Observation",
    "Posterior",
    "Check",
    "Forecast",
    "Estimator",
    "Stream",
    "LoopStream",
    "POSITION_NOW",
    "observed_positions",
    "prior_posterior",
    "MethodSpec",
    "MAX_HORIZON",
    "DT_RANGE",
    "BOX_MARGIN",
    "MIN_FRAME_SIDE",
    "check_frame",
    "check_stream_floor",
    "frame_rate_of",
    "frame_cap_of",
    "EXPENSIVE_MAX_FRAMES",
]

#: Longest forecast any method makes (frames): 100 s at the paper's 20 frames/s, ten videos.
#: A longer ``horizon`` raises ``ValueError`` naming it (checked for every method by the base).
MAX_HORIZON = 2000
#: Smallest frame height and width (pixels) a video may have.
MIN_FRAME_SIDE = 4
#: Most observations an expensive-tier method (NUTS, BO) takes from a camera's clip unless it
#: declares its own ``max_frames``: twice the benchmark's 200-frame videos its cost was tuned on
#: (NUTS on a pendulum: 37 CPU-s at 200 frames; a 10 s clip at 240 fps is 2400)
EXPENSIVE_MAX_FRAMES = 400


@dataclass
class Observation:
    """A video and/or a track of one ball.

    Parameters
    ----------
    frames : ndarray, shape (T, H, W), optional
        Grey-scale frames (uint8, or floats in [0, 255]). Stored as given.
    positions : ndarray, shape (T, 2), optional
        Ball centre ``[x, y]`` in metres at each frame; NaN where the ball is not seen.
    dt : float
        Seconds between frames.
    floor : float, optional
        Floor height in metres; ``None`` means unknown.
    state0 : ndarray, shape (4,), optional
        Known initial state ``[x, y, vx, vy]`` (the paper's privileged baselines); ``None`` means
        the method must estimate it.
    system : str
        The registered system seen (:mod:`sysid_bench.core.systems`), ``"ball"`` by default. For
        another system ``positions`` are its K tracked points, shape (T, K, 2) ((T, 2) is read
        as K = 1 and stored as (T, 1, 2)), ``state0`` is its state (S,), and positions are
        checked against the system's view instead of the ball's box. The ball keeps (T, 2)
        ((T, 1, 2) is accepted and stored as (T, 2)).
    scene : sysid_bench.core.systems.Scene, optional
        The system's known geometry in metres (``systems.get(system).scene(...)``: the ball's
        floor and walls, the pendulum's pivot, the spring's anchor, the collision track's ends
        and the pucks' half-sizes). ``None`` means the system's default scene (the design's
        numbers). Checked on construction: another system's scene or a non-scene is a
        ``TypeError``, a non-finite value a ``ValueError``; the ball's ``floor``, where both are
        given, must equal the scene's. With a scene other than the default, positions and
        ``state0`` are checked against the scene (the walls and floor that exist, the state
        bounds it implies) instead of the default box or view.
    known : dict of str -> float, optional
        Parameters the user knows, held fixed (``{"g": -9.81}``): a method that takes
        ``known`` answers conditional on them (as ``methods.get(name, known=...)``; the two
        must agree where both name a parameter), a method that cannot hold them refuses the
        observation with its reason. Names are the system's parameters; values finite.
    """

    frames: np.ndarray | None = None
    positions: np.ndarray | None = None
    dt: float = 0.05
    floor: float | None = None
    state0: np.ndarray | None = None
    system: str = "ball"
    scene: Any = None
    known: dict | None = None

    def _checked_scene(self):
        """The validated scene (None stays None) and whether it is the system's default."""
        if self.scene is None:
            return None, True
        from sysid_bench.core import systems  # local: only an observation with a scene needs it

        sys_ = systems.get(self.system)
        sc = sys_.check_scene(self.scene, "scene")
        return sc, sc == sys_.default_scene

    def __post_init__(self) -> None:
        if self.frames is None and self.positions is None:
            raise ValueError("Observation: expected frames and/or positions, got neither")
        if self.frames is not None:
            fr = np.asarray(self.frames)
            if fr.ndim != 3:
                raise ValueError(
                    f"frames: expected a (T, H, W) array, got shape {fr.shape} dtype {fr.dtype}"
                )
            if fr.dtype != np.uint8:
                fr = as_float_array(fr, "frames", ndim=3)
                if fr.min() < 0 or fr.max() > 255:
                    raise ValueError(
                        f"frames: expected values in [0, 255], got [{fr.min():g}, {fr.max():g}]"
                    )
            if fr.shape[0] < 1:
                raise ValueError("frames: expected at least 1 frame, got 0")
            if min(fr.shape[1:]) < MIN_FRAME_SIDE:
                raise ValueError(
                    f"frames: expected frames of at least {MIN_FRAME_SIDE}x{MIN_FRAME_SIDE} pixels, "
                    f"got shape {fr.shape}"
                )
            self.frames = fr
        from sysid_bench.core import systems  # local: systems sit above the estimator's helpers

        sys_ = systems.get(self.system)  # ValueError listing the known systems
        self.system = sys_.name
        self.scene, default_scene = self._checked_scene()
        self.known = _checked_known(self.known, sys_)
        # the system's own checks of the other fields (the ball's box and floor, another
        # system's view and state): System.check_observation
        sys_.check_observation(self, default_scene)

    @property
    def points(self) -> np.ndarray | None:
        """Positions as (T, K, 2) for every system (the ball's (T, 2) with K = 1), or None."""
        if self.positions is None:
            return None
        return self.positions if self.positions.ndim == 3 else self.positions[:, None, :]

    @property
    def n_frames(self) -> int:
        """Number of observed frames T."""
        src = self.frames if self.frames is not None else self.positions
        return int(src.shape[0])

    @property
    def frame_shape(self) -> tuple[int, int] | None:
        """(H, W) of the frames, or None when only positions are given."""
        return None if self.frames is None else tuple(self.frames.shape[1:])

    def prefix(self, n: int) -> Observation:
        """The first ``n`` frames of this observation (same dt, floor, state0 and scene)."""
        n = check_positive_int(n, "n")
        if n > self.n_frames:
            raise ValueError(f"n: expected at most {self.n_frames} frames, got {n}")
        return Observation(
            frames=None if self.frames is None else self.frames[:n],
            positions=None if self.positions is None else self.positions[:n],
            dt=self.dt,
            floor=self.floor,
            state0=self.state0,
            system=self.system,
            scene=self.scene,
            known=self.known,
        )


def _checked_known(known, sys_) -> dict[str, float] | None:
    """``Observation.known`` checked against the system: None or a dict of its parameter names
    to finite numbers (an empty dict reads as None)."""
    if known is None:
        return None
    if not isinstance(known, dict):
        raise ValueError(f"known: expected a dict of parameter name -> value, got "
                         f"{type(known).__name__} {known!r}")
    out = {}
    for name, v in known.items():
        if name not in sys_.params:
            raise ValueError(f"known: expected parameters of the {sys_.name} system "
                             f"({', '.join(sys_.params)}), got {name!r}")
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not np.isfinite(v):
            raise ValueError(f"known: expected a finite number for {name}, got {v!r}")
        out[str(name)] = float(v)
    return out or None


def _with_knowledge(est, obs):
    """The estimator that answers ``obs``: ``est`` itself, or, where ``obs.known`` holds
    values, a copy built from ``est``'s hyperparameters holding them too. A method without a
    ``known`` hyperparameter refuses, naming its ``knowledge_refused`` reason; a value that
    contradicts the estimator's own ``known`` is refused."""
    known = getattr(obs, "known", None)
    if not known:
        return est
    params = est.get_params()
    if "known" not in params:
        why = getattr(type(est), "knowledge_refused", "it takes no known values")
        raise ValueError(f"obs.known: {est.name} cannot hold known values ({why}); got "
                         f"{known!r}")
    mine = {str(k): float(v) for k, v in (params.get("known") or {}).items()}
    clash = [f"{k} = {v:g} (the estimator holds {mine[k]:g})" for k, v in known.items()
             if k in mine and mine[k] != v]
    if clash:
        raise ValueError(f"obs.known: contradicts the estimator's known values: "
                         f"{'; '.join(clash)}")
    if known.keys() <= mine.keys():  # already held (a copy's own prefixes): no second copy
        return est
    return type(est)(**{**params, "known": {**mine, **known}})


def _system_name(system) -> str:
    """A registered system's name (``ValueError`` with the known ones, and "did you mean")."""
    from sysid_bench.core import systems

    return systems.get(system).name


def _system_params(system) -> tuple[str, ...]:
    """Parameter names of a registered system."""
    from sysid_bench.core import systems

    return tuple(systems.get(system).params)


def observed_positions(obs: Observation, *, min_seen: int = 3) -> np.ndarray:
    """Positions a position-based method should use, tracking the frames when needed.

    Parameters
    ----------
    obs : Observation
    min_seen : int
        Fewest frames where the ball must be seen.

    Returns
    -------
    ndarray, shape (T, 2)
        Metres, NaN where unseen.

    Raises
    ------
    ValueError
        Fewer than ``min_seen`` seen frames. (Positions more than ``BOX_MARGIN`` outside the box
        are refused by ``Observation``; those within it are moved onto the box's edge here.)
    """
    if obs.positions is not None:
        pos = obs.positions.copy()
    else:
        from sysid_bench.core.tracking import (
            track,  # local: tracking is only needed for video input
        )

        pos = track(obs.frames, floor=0.0 if obs.floor is None else obs.floor)
    # a ball touching a wall or the floor can be seen a few mm outside the box: that is tracking
    # error, not bad input (Observation rejects more than BOX_MARGIN), so it is moved onto the edge
    pos[:, 0] = np.clip(pos[:, 0], 0.0, BOX_WIDTH)
    if obs.floor is not None:
        pos[:, 1] = np.clip(pos[:, 1], obs.floor, obs.floor + BOX_WIDTH)
    seen = np.isfinite(pos).all(axis=1)
    if seen.sum() < min_seen:
        raise ValueError(
            f"positions: expected the ball seen in at least {min_seen} frames, "
            f"got {int(seen.sum())} of {pos.shape[0]}"
        )
    return pos


#: A posterior-mean trajectory fits when its residual RMS is within this factor of the noise the
#: method assumed (or the chi-square bound below, if larger). Generous on purpose: tracking error
#: and a method's coarse noise model differ by up to ~1.5x on our own clean cases; a model that
#: does not explain the observation misses by 10-100x (a hovering ball: 1.7 m against 0.02 m).
CHECK_FACTOR = 2.0


@dataclass(frozen=True)
class Check:
    """Does the model explain the observation? (``Posterior.check``)

    Parameters
    ----------
    rms_m : float
        Residual RMS (m) against the observed positions of the trajectory that was judged: the
        posterior mean's; when that fails and a parameter vector inside the posterior's 90%
        interval explains the track (``methods._simulation.check_posterior``), that one's.
    noise_m : float
        The observation noise (m) the method assumed.
    ok : bool
        ``rms_m`` within what ``noise_m`` explains. A posterior whose check fails never claims
        precision: its method widens the intervals or says so here.
    n : int
        Number of residuals (coordinates of seen points) behind ``rms_m``.
    note : str
        Which trajectory passed ("passes at the posterior mean", "passes inside the 90%
        interval"), or what was done about a failed check (e.g. "intervals widened to the
        prior").
    """

    rms_m: float
    noise_m: float
    ok: bool
    n: int = 0
    note: str = ""

    def __post_init__(self) -> None:
        for name in ("rms_m", "noise_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name}: expected a number of metres, got {v!r}")
            if not (np.isnan(v) or v >= 0):
                raise ValueError(f"{name}: expected >= 0 m or NaN, got {v!r}")
        if not isinstance(self.ok, (bool, np.bool_)):
            raise ValueError(f"ok: expected a bool, got {self.ok!r}")

    @classmethod
    def from_residuals(cls, residuals, noise_m: float, *, factor: float = CHECK_FACTOR,
                       note: str = "") -> Check:
        """The check of residuals (any shape, metres, NaN = unseen) against ``noise_m``.

        Passes when the RMS is at most ``max(factor, sqrt(chi2_0.999(n) / n))`` times
        ``noise_m``: the chi-square bound keeps a short track's honest fit from failing by chance.
        No residual at all (nothing seen) fails: nothing explains nothing.
        """
        r = np.asarray(residuals, dtype=np.float64).ravel()
        r = r[np.isfinite(r)]
        noise = float(noise_m)
        if r.size == 0:
            return cls(float("nan"), noise, False, 0, note or "nothing observed")
        rms = float(np.sqrt(np.mean(r * r)))
        return cls(rms, noise, bool(rms <= cls.bound(r.size, factor) * noise), int(r.size), note)

    @staticmethod
    def bound(n: int, factor: float = CHECK_FACTOR) -> float:
        """The largest passing RMS of ``n`` residuals, in units of the noise:
        ``max(factor, sqrt(chi2_0.999(n) / n))``."""
        from scipy.stats import chi2

        n = int(n)
        if n < 1:
            raise ValueError(f"n: expected at least 1 residual, got {n!r}")
        return max(float(factor), float(np.sqrt(chi2.ppf(0.999, n) / n)))

    def as_dict(self) -> dict[str, Any]:
        """``{"check_ok": ..., "check_rms_m": ..., "check_noise_m": ...}`` for tables."""
        return {"check_ok": bool(self.ok), "check_rms_m": float(self.rms_m),
                "check_noise_m": float(self.noise_m)}


@dataclass
class Posterior:
    """A method's belief about the physical parameters, in physical units, ``PARAMS`` order.

    Parameters
    ----------
    mean : ndarray, shape (4,)
    std : ndarray, shape (4,)
        Non-negative; ``inf`` is allowed and means "no information".
    samples : ndarray, shape (S, 4), optional
    extras : dict
        ``n_simulations`` (int), ``wall_s`` (float) and method diagnostics (R-hat, ESS, ...).
    check : Check, optional
        Whether the model explains the observation (``None`` only for a method that cannot
        tell; its ``extras["check_reason"]`` says why).
    """

    mean: np.ndarray
    std: np.ndarray
    samples: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)
    check: Check | None = None
    system: str = "ball"

    def __post_init__(self) -> None:
        names = _system_params(self.system)
        if not isinstance(self.system, str):
            self.system = _system_name(self.system)
        p = len(names)
        self.mean = as_float_array(self.mean, "mean", ndim=1, last=p)
        from sysid_bench.core import systems

        systems.get(self.system).check_posterior_mean(self.mean)
        std = _as_std(self.std)
        if std.shape != (p,):
            raise ValueError(f"std: expected shape ({p},) ({self.system}: {', '.join(names)}), got {std.shape}")
        self.std = std
        if self.samples is not None:
            self.samples = as_float_array(self.samples, "samples", ndim=2, last=p)
        if not isinstance(self.extras, dict):
            raise ValueError(f"extras: expected a dict, got {type(self.extras).__name__}")
        if self.check is not None and not isinstance(self.check, Check):
            raise ValueError(f"check: expected a Check or None, got {type(self.check).__name__}")

    def interval(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """Central interval holding ``level`` of the mass, per parameter.

        Uses the samples' quantiles when there are samples, else the Gaussian N(mean, std).

        Returns
        -------
        lo, hi : ndarray, shape (4,)
        """
        level = check_number(level, "level")
        if not 0 < level < 1:
            raise ValueError(f"level: expected a number in (0, 1), got {level!r}")
        a = (1 - level) / 2
        if self.samples is not None and len(self.samples) >= 2:
            lo, hi = np.quantile(self.samples, [a, 1 - a], axis=0)
            return lo, hi
        z = float(central_z(level))
        return self.mean - z * self.std, self.mean + z * self.std

    def as_dict(self) -> dict[str, float]:
        """``{"e": mean_e, ..., "e_std": std_e, ...}`` for tables."""
        names = _system_params(self.system)
        out = {p: float(m) for p, m in zip(names, self.mean)}
        out.update({f"{p}_std": float(s) for p, s in zip(names, self.std)})
        return out


@dataclass
class Forecast:
    """Predicted positions for the ``H`` frames after an observation.

    Parameters
    ----------
    mean : ndarray, shape (H, 2) or (H, K, 2)
        Metres: (H, 2) for a system with one tracked point (the ball), (H, K, 2) for K > 1.
    std : ndarray, same shape as ``mean``
    samples : ndarray, shape (S, *mean.shape), optional
    extras : dict
    """

    mean: np.ndarray
    std: np.ndarray
    samples: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.mean = as_float_array(self.mean, "mean", ndim=(2, 3), last=2)
        if self.mean.shape[0] < 1:  # a forecast of nothing answers no question
            raise ValueError(f"mean: expected a horizon of at least 1 frame, got shape "
                             f"{self.mean.shape}")
        std = _as_std(self.std)
        if std.shape != self.mean.shape:
            raise ValueError(f"std: expected shape {self.mean.shape}, got {std.shape}")
        self.std = std
        if self.samples is not None:
            s = as_float_array(self.samples, "samples", ndim=self.mean.ndim + 1, last=2)
            if s.shape[1:] != self.mean.shape:
                raise ValueError(
                    f"samples: expected shape (S, {', '.join(map(str, self.mean.shape))}) like mean, "
                    f"got shape {s.shape}"
                )
            self.samples = s
        if not isinstance(self.extras, dict):
            raise ValueError(f"extras: expected a dict, got {type(self.extras).__name__}")

    @property
    def horizon(self) -> int:
        return int(self.mean.shape[0])


def _as_std(std) -> np.ndarray:
    """A result's standard deviations: real, non-negative; ``inf`` allowed (no information)."""
    try:
        arr = np.asarray(std, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"std: expected non-negative numbers, got {std!r} ({exc})") from None
    if not (arr >= 0).all():  # NaN and negatives (one pass: NaN >= 0 is False)
        raise ValueError(f"std: expected non-negative values (inf for none), got {arr}")
    return arr


def prior_posterior(n_samples: int = 0, seed=0, system: str = "ball", **extras) -> Posterior:
    """A system's uniform prior as a Posterior: what a method knows before seeing anything.

    Parameters
    ----------
    n_samples : int
        Prior draws to attach as ``samples`` (0 for none).
    seed : int or Generator
    system : str
        The registered system whose prior it is.
    **extras
        Put into ``Posterior.extras`` (``n_simulations`` defaults to 0, ``wall_s`` to 0.0).
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    lo, hi = np.asarray(sys_.prior_lo, float), np.asarray(sys_.prior_hi, float)
    samples = None
    n_samples = check_int(n_samples, "n_samples", lo=0)
    if n_samples:
        rng = check_seed(seed)
        samples = lo + rng.random((n_samples, lo.size)) * (hi - lo)
    info = {"n_simulations": 0, "wall_s": 0.0}
    info.update(extras)
    return Posterior(mean=(lo + hi) / 2, std=(hi - lo) / np.sqrt(12.0), samples=samples,
                     extras=info, system=sys_.name)


#: Key of a stream forecast's ``extras``: where the stream's fit puts the ball at the latest
#: frame pushed, shape (2,), metres in the stream's own frame (see :meth:`Stream.forecast`).
POSITION_NOW = "position_now_m"


def check_frame(frame, name: str = "frame") -> np.ndarray:
    """One video frame as a stream takes it: ``ValueError`` naming ``name`` unless it is a real
    numeric (H, W) array (not bool), both sides at least :data:`MIN_FRAME_SIDE` pixels, and --
    unless uint8 -- finite with values in [0, 255] (the rules :class:`Observation` applies to
    ``frames``).

    Returns
    -------
    ndarray, shape (H, W)
        ``np.asarray(frame)``, values and dtype as given (no copy, no conversion: a stream's
        numbers stay those of the frame it was given).
    """
    try:
        fr = np.asarray(frame)
    except Exception as exc:  # ragged nested lists and the like
        raise ValueError(f"{name}: expected an (H, W) numeric array, got {type(frame).__name__} "
                         f"({exc})") from None
    if fr.dtype != np.uint8 and (fr.dtype == object or fr.dtype == np.bool_
                                 or not np.issubdtype(fr.dtype, np.number)
                                 or np.iscomplexobj(fr)):
        raise ValueError(f"{name}: expected a real numeric (H, W) array (uint8, or floats in "
                         f"[0, 255]), got dtype {fr.dtype} shape {fr.shape}")
    if fr.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) array, got shape {fr.shape}")
    if min(fr.shape) < MIN_FRAME_SIDE:
        raise ValueError(f"{name}: expected a frame of at least {MIN_FRAME_SIDE}x{MIN_FRAME_SIDE} "
                         f"pixels, got shape {fr.shape}")
    if fr.dtype != np.uint8:
        bad = ~np.isfinite(fr)
        if bad.any():
            what = "NaN" if np.isnan(fr[bad]).any() else "inf"
            raise ValueError(f"{name}: expected finite values in [0, 255], got {what} in "
                             f"{int(bad.sum())} pixels")
        lo, hi = fr.min(), fr.max()
        if lo < 0 or hi > 255:
            raise ValueError(f"{name}: expected values in [0, 255], got [{lo:g}, {hi:g}]")
    return fr


def check_stream_floor(floor) -> float | None:
    """A stream forecast's ``floor`` offset: None, or a finite number of metres within
    ``+-physics.FLOOR_MAX`` (what an Observation's floor may be); ``ValueError`` naming it."""
    if floor is None:
        return None
    return check_number(floor, "floor", lo=-FLOOR_MAX, hi=FLOOR_MAX, unit="m")


def _checking_push(push):
    @functools.wraps(push)
    def wrapper(self, frame, *args, **kwargs):
        # before the stream's own push touches its state: a refused frame leaves it as it was
        return push(self, check_frame(frame, "frame"), *args, **kwargs)

    return wrapper


def _checking_stream_forecast(forecast):
    @functools.wraps(forecast)
    def wrapper(self, horizon, floor=None, *args, **kwargs):
        horizon = check_horizon(horizon, MAX_HORIZON)
        return forecast(self, horizon, check_stream_floor(floor), *args, **kwargs)

    return wrapper


class Stream(abc.ABC):
    """Online identification: push one frame at a time, read the posterior after each.

    Beside ``reset`` and ``push`` a stream tells how many frames it holds (``n_frames``) and
    where it puts the ball now (:meth:`position`); a stream of a method that forecasts also
    forecasts from the frames it holds (:meth:`forecast`). A method whose stream is recurrent
    (a push costs the same at every frame) declares ``online`` (:mod:`sysid_bench.core.spec`);
    :func:`sysid_bench.core.testing.check_estimator` checks all of this. The interception policy
    and the online-cost table read streams only through it.

    The base checks, for every stream, what its own ``push`` and ``forecast`` are given before
    they run: the frame (:func:`check_frame`: a real numeric (H, W) array, finite, in [0, 255],
    at least ``MIN_FRAME_SIDE`` a side; the stream itself checks it matches the frames before
    it), ``horizon`` in ``[1, MAX_HORIZON]`` and ``floor`` (:func:`check_stream_floor`). A
    refused frame raises ``ValueError`` naming ``frame`` and leaves the stream as it was.
    """

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        # every stream gets the shared argument checks without calling them itself
        if "push" in cls.__dict__:
            cls.push = _checking_push(cls.__dict__["push"])
        if "forecast" in cls.__dict__:
            cls.forecast = _checking_stream_forecast(cls.__dict__["forecast"])

    @abc.abstractmethod
    def reset(self) -> None:
        """Forget every frame pushed so far."""

    @abc.abstractmethod
    def push(self, frame: np.ndarray) -> Posterior:
        """Add one frame of shape (H, W) and return the posterior given all frames so far."""

    @property
    def n_frames(self) -> int:
        """Frames pushed since the last ``reset``."""
        raise NotImplementedError(f"{type(self).__name__} does not count its frames")

    def position(self) -> np.ndarray:
        """The stream's position of the ball at the latest frame pushed.

        Returns
        -------
        ndarray, shape (2,)
            ``(x, y)`` in metres, in the stream's own frame (for a model that infers the floor
            from the bounces, heights above that floor); NaN where the ball is not known. On a
            system with K > 1 tracked points, the first point's.
        """
        raise NotImplementedError(f"{type(self).__name__} does not report a position")

    def forecast(self, horizon: int, floor: float | None = None) -> Forecast:
        """Positions of the ``horizon`` frames after the latest one pushed.

        Parameters
        ----------
        horizon : int
            Frames to predict, in ``[1, MAX_HORIZON]``.
        floor : float, optional
            Offset (m) added to the forecast heights, which are in the stream's own frame (that
            of :meth:`position`); 0 when None. At most ``physics.FLOOR_MAX`` in magnitude.

        Returns
        -------
        Forecast
            ``mean`` and ``std`` of shape (horizon, 2) ((horizon, K, 2) on a system with K > 1
            tracked points); ``extras[POSITION_NOW]`` (2,) is where the forecast's fit puts the
            ball (the first point) at the latest frame, in the same frame.
        """
        raise NotImplementedError(f"{type(self).__name__} does not forecast")

    def check(self) -> Posterior:
        """The posterior after the latest frame pushed, with its model check
        (``Posterior.check``) and widened where it fails, as ``identify`` answers.

        A recurrent stream's ``push`` answers without a check (one costs a least-squares fit,
        ~100 pushes); a caller that acts on a posterior asks for its check here.
        """
        raise NotImplementedError(f"{type(self).__name__} does not check its posteriors")


class LoopStream(Stream):
    """Stream for methods with no recurrent state: re-identifies on all frames so far.

    Cost grows with the number of frames; Vid2Param's own stream is constant per frame. The
    observations it builds are of the estimator's own system (``estimator.system``, the ball
    when it has none), with ``dt`` and ``floor``; before the estimator's ``min_frames`` frames
    it answers that system's prior.

    Parameters
    ----------
    estimator : Estimator
    dt : float
        Seconds between frames, in ``DT_RANGE``.
    floor : float, optional
        The observation's floor (m), as ``Observation.floor``; None: unknown.
    """

    def __init__(self, estimator: Estimator, dt: float = 0.05, floor: float | None = None):
        if not isinstance(estimator, Estimator):
            raise ValueError(f"estimator: expected an Estimator, got {type(estimator).__name__}")
        self.estimator = estimator
        self.dt = check_number(dt, "dt", lo=DT_RANGE[0], hi=DT_RANGE[1], unit="s")
        self.floor = None if floor is None else check_number(
            floor, "floor", lo=-FLOOR_MAX, hi=FLOOR_MAX, unit="m")
        self.reset()

    @property
    def system(self) -> str:
        """The registered system the estimator identifies (``"ball"`` when it names none)."""
        sys_ = getattr(self.estimator, "system", "ball")
        return sys_ if isinstance(sys_, str) else _system_name(sys_)

    def reset(self) -> None:
        self._frames: list[np.ndarray] = []
        self._last: Posterior | None = None

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def _observation(self) -> Observation:
        """Every frame pushed, as an Observation of the estimator's system."""
        return Observation(frames=np.stack(self._frames), dt=self.dt, floor=self.floor,
                           system=self.system)

    def _prior(self, note: str) -> Posterior:
        """The system's uniform prior as a Posterior (:func:`prior_posterior`)."""
        return prior_posterior(system=self.system, note=note)

    def check(self) -> Posterior:
        """The latest posterior: ``identify``'s, checked already (the prior's before
        ``min_frames`` frames)."""
        if self._last is None:
            raise ValueError("check: push at least one frame first (stream.push(frame))")
        return self._last

    def position(self) -> np.ndarray:
        """The ball (on another system: the first tracked point) tracked in the latest frame
        (the ball: :func:`sysid_bench.core.tracking.track`; else the system's ``track``; a method
        re-identifying from scratch keeps no filtered state), NaN before the first frame."""
        if not self._frames:
            return np.full(2, np.nan)
        from sysid_bench.core import systems  # local: as in Observation

        return np.asarray(systems.get(self.system).track_observed(self._frames[-1][None],
                                                                  floor=self.floor),
                          dtype=np.float64)[0, 0]

    def forecast(self, horizon: int, floor: float | None = None) -> Forecast:
        """The estimator's forecast on every frame pushed, heights shifted by ``floor``;
        ``extras[POSITION_NOW]`` is :meth:`position`."""
        if not self._frames:
            raise ValueError("forecast: push at least one frame first (stream.push(frame))")
        fc = self.estimator.forecast(self._observation(), horizon)
        off = np.array([0.0, 0.0 if floor is None else float(floor)])
        now = self.position() + off
        return Forecast(mean=fc.mean + off, std=fc.std, samples=None if fc.samples is None
                        else fc.samples + off, extras={**fc.extras, POSITION_NOW: now})

    def push(self, frame: np.ndarray) -> Posterior:
        """Add one (H, W) frame (checked by the base, and here against the first frame's shape;
        a refused frame is not kept) and re-identify on every frame so far."""
        fr = np.asarray(frame)
        if self._frames and fr.shape != self._frames[0].shape:
            raise ValueError(
                f"frame: expected shape {self._frames[0].shape} like the earlier frames, got {fr.shape}"
            )
        self._frames.append(fr)
        if len(self._frames) < self.estimator.min_frames:
            self._last = self._prior(f"fewer than {self.estimator.min_frames} frames: the prior")
        else:
            self._last = self.estimator.identify(self._observation())
        return self._last


_SPECS: dict[type, MethodSpec] = {}


class Estimator(abc.ABC):
    """Base class of every method.

    Subclasses set ``name`` and ``input_kind``, take keyword-only hyperparameters in
    ``__init__`` that they store under the same attribute names (no work there), and implement
    ``identify`` and, where they can, ``forecast``. A method that cannot do something raises
    ``NotImplementedError`` with a sentence saying why; benchmarks record that as "n/a".

    What the harness needs to know about a method is declared here as class attributes, with
    defaults (see :mod:`sysid_bench.core.spec`); :meth:`spec` returns them checked, as one frozen
    record. The base also checks, for every method: the hyperparameters after ``__init__`` and
    ``set_params`` (``seed``, and the subclass's own ``_validate``), that ``obs`` is an
    Observation, and that ``horizon`` lies in ``[1, MAX_HORIZON]``.
    """

    # -- declarations (sysid_bench.core.spec documents each) --------------------------------------
    name: str = "estimator"
    #: "positions" when the method works on tracked positions, "frames" when on pixels.
    input_kind: str = "positions"
    #: Fewest frames ``identify`` accepts; a default stream answers the prior before that.
    min_frames: int = 1
    identifies: bool = True
    forecasts: bool = False
    streams: bool = False
    online: bool = False
    trains: bool = False
    cost: int = 10
    scale_cases: dict = MappingProxyType({})
    scale_options: dict = MappingProxyType({})
    fit_options: dict = MappingProxyType({})
    pretrained: dict = MappingProxyType({})
    threads_param: str | None = None
    inline: bool = False
    online_cost: bool = False
    policies: dict = MappingProxyType({})
    from_paper: bool = False
    paper_baseline: bool = False
    reference_posterior: bool = False
    #: The systems the method runs on: a tuple of registered names, or ``"any"`` (every
    #: registered system, one a user registers included); :func:`methods.get` refuses the others
    systems: tuple | str = ("ball",)
    contract_options: dict = MappingProxyType({})
    #: The frame rate (frames/s) the method is built for, or None: it simulates at any step
    #: and takes a camera's clip at the capture's own ``dt``. A method with a rate (Vid2Param's
    #: networks saw 20 frames/s) gets every clip resampled to it, and ``identify`` says so.
    #: Read through :func:`frame_rate_of`; not part of :meth:`spec` (the fingerprint's
    #: declarations), since it changes no figure of a simulated case.
    frame_rate: float | None = None
    #: The most observations the method takes from a camera's clip (None: every one; an
    #: expensive-tier method, ``cost >= EXPENSIVE_COST``, defaults to
    #: :data:`EXPENSIVE_MAX_FRAMES`): a longer clip is thinned to every k-th frame at k times
    #: the dt, and ``identify`` says so. Read through :func:`frame_cap_of`; not in :meth:`spec`.
    max_frames: int | None = None

    @classmethod
    def spec(cls) -> MethodSpec:
        """The class's declarations, checked once (``ValueError`` naming a bad one)."""
        sp = _SPECS.get(cls)
        if sp is None:
            sp = _SPECS[cls] = spec_of(cls)
        return sp

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        # every method gets the shared argument checks without calling them itself
        if "__init__" in cls.__dict__:
            cls.__init__ = _validating_init(cls.__dict__["__init__"])
        if "identify" in cls.__dict__:
            cls.identify = _checking_identify(cls.__dict__["identify"])
        if "forecast" in cls.__dict__:
            cls.forecast = _checking_forecast(cls.__dict__["forecast"])
        if "fit" in cls.__dict__:
            cls.fit = _checking_fit(cls.__dict__["fit"])
        if "identify_prefixes" in cls.__dict__:
            cls.identify_prefixes = _checking_prefixes(cls.__dict__["identify_prefixes"])

    def _validate(self) -> None:
        """Check the stored hyperparameters; ``ValueError`` naming the first bad one.

        Subclasses extend it (call ``super()._validate()``) with ranges; the base checks every
        hyperparameter's type against its constructor annotation (``bool`` a real flag, ``int``
        no float, ``float`` no string or bool; :func:`sysid_bench.core._validate.check_annotated`)
        and the seed. It runs after ``__init__`` and ``set_params`` (which keeps nothing it
        refused), so a bad value fails where it is given, and again at ``identify``,
        ``forecast`` and ``fit``, so a value set on the instance directly fails before use.
        """
        params = self.get_params()
        for name, ann in _annotations(type(self)).items():
            if name != "seed" and name in params:
                check_annotated(params[name], name, ann)
        if "seed" in params:
            check_seed_value(self.seed, "seed")

    # -- hyperparameters (scikit-learn style) -------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        names = _PARAM_NAMES.get(cls)
        if names is None:  # once per class: inspect.signature costs ~0.1 ms, paid per identify
            sig = inspect.signature(cls.__init__)
            names = _PARAM_NAMES[cls] = [
                p.name
                for p in sig.parameters.values()
                if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
            ]
        return list(names)

    def get_params(self) -> dict[str, Any]:
        """Hyperparameters as given to the constructor."""
        return {k: getattr(self, k) for k in self._param_names()}

    def set_params(self, **params) -> Estimator:
        """Set hyperparameters; a refused value (``ValueError``) leaves every one as it was."""
        names = self._param_names()
        for k in params:
            if k not in names:
                raise ValueError(f"{k}: not a hyperparameter of {self.name}; known: {names}")
        old = {k: getattr(self, k) for k in params}
        for k, v in params.items():
            setattr(self, k, v)
        try:
            self._validate()
        except BaseException:
            for k, v in old.items():
                setattr(self, k, v)
            raise
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    # -- the interface ----------------------------------------------------------------------
    def fit(self, train=None) -> Estimator:
        """Train on a dataset; methods that do not learn return ``self`` unchanged."""
        _check_train(train)
        return self

    @abc.abstractmethod
    def identify(self, obs: Observation) -> Posterior:
        """Posterior over ``(e, g, d, r)`` given the whole observation."""

    def identify_prefixes(self, obs: Observation, lengths) -> list[Posterior]:
        """Posteriors after each of ``lengths`` frames. Default: one ``identify`` per prefix."""
        lengths = _check_lengths(obs, lengths)
        return [self.identify(obs.prefix(n)) for n in lengths]

    def identify_prefixes_batch(self, observations, lengths,
                                check: bool = True) -> list[list[Posterior]]:
        """Posteriors after each of ``lengths`` frames of each observation.

        Default: :meth:`identify_prefixes` on each. A method that answers many videos in one
        pass (a network) overrides it; its answers must equal the default's to float rounding
        (``sysid_bench.core.testing.check_prefixes``).

        Parameters
        ----------
        observations : sequence of Observation
        lengths : sequence of int
        check : bool
            False: the caller scores the posterior means alone, so a method that model-checks
            separately from identifying may skip its check (``Posterior.check`` None then);
            the default ignores it.

        Returns
        -------
        list (one per observation) of list (one per length) of Posterior
        """
        obs = list(observations)
        for i, o in enumerate(obs):
            if not isinstance(o, Observation):
                raise ValueError(f"observations[{i}]: expected an Observation, got "
                                 f"{type(o).__name__}")
        return [self.identify_prefixes(o, lengths) for o in obs]

    def forecast(self, obs: Observation, horizon: int) -> Forecast:
        """Positions of the ``horizon`` frames after the observation (``horizon`` <= MAX_HORIZON)."""
        raise NotImplementedError(f"{self.name} does not forecast positions.")

    def stream(self) -> Stream:
        """Frame-by-frame identification; default re-identifies on every prefix."""
        return LoopStream(self)


def frame_rate_of(method) -> float | None:
    """The frame rate a method is built for (its ``frame_rate`` declaration), checked.

    Parameters
    ----------
    method : Estimator or Estimator subclass

    Returns
    -------
    float or None
        Frames/s every clip is resampled to for this method; None when it simulates at any
        step (a camera's clip then keeps the capture's own ``dt``).

    Raises
    ------
    TypeError
        ``method`` is not an Estimator or Estimator subclass.
    ValueError
        A declared rate that is not a finite number > 0; the message names ``Class.frame_rate``.
    """
    cls = method if isinstance(method, type) else type(method)
    if not issubclass(cls, Estimator):
        raise TypeError(f"method: expected an Estimator or Estimator subclass, got "
                        f"{cls.__name__}")
    rate = cls.frame_rate
    if rate is None:
        return None
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (
            math.isfinite(float(rate)) and float(rate) > 0):
        raise ValueError(f"{cls.__name__}.frame_rate: expected None or frames/s > 0, got "
                         f"{rate!r}")
    return float(rate)


def frame_cap_of(method) -> int | None:
    """The most observations a method takes from a camera's clip (its ``max_frames``).

    Parameters
    ----------
    method : Estimator or Estimator subclass

    Returns
    -------
    int or None
        The declared ``max_frames``; else :data:`EXPENSIVE_MAX_FRAMES` for an expensive-tier
        method (``spec().expensive``); else None (every frame).

    Raises
    ------
    TypeError
        ``method`` is not an Estimator or Estimator subclass.
    ValueError
        A declared cap that is not an int >= 3; the message names ``Class.max_frames``.
    """
    cls = method if isinstance(method, type) else type(method)
    if not issubclass(cls, Estimator):
        raise TypeError(f"method: expected an Estimator or Estimator subclass, got "
                        f"{cls.__name__}")
    cap = cls.max_frames
    if cap is None:
        return EXPENSIVE_MAX_FRAMES if cls.spec().expensive else None
    if isinstance(cap, bool) or not isinstance(cap, int) or cap < 3:
        raise ValueError(f"{cls.__name__}.max_frames: expected None or an int >= 3, got "
                         f"{cap!r}")
    return cap


def _check_obs(obs, est=None) -> None:
    if not isinstance(obs, Observation):
        raise ValueError(f"obs: expected a sysid_bench.core.estimator.Observation, got {type(obs).__name__}")
    # a method built for one system must not read another system's observation as its own
    want = getattr(est, "system", "ball") if est is not None else obs.system
    if isinstance(want, str) and want != obs.system:
        raise ValueError(
            f"obs: expected an observation of the {want} system for this {getattr(est, 'name', '')} "
            f"estimator, got one of the {obs.system} system (methods.get(name, system="
            f"{obs.system!r}) builds the method for it)"
        )


def _annotations(cls) -> dict[str, Any]:
    """Constructor annotations of ``cls``'s hyperparameters (``name -> annotation``)."""
    got = _ANNOTATIONS.get(cls)
    if got is None:
        sig = inspect.signature(cls.__init__)
        got = _ANNOTATIONS[cls] = {p.name: p.annotation for p in sig.parameters.values()
                                   if p.name != "self" and p.annotation is not p.empty}
    return got


_ANNOTATIONS: dict[type, dict[str, Any]] = {}
_PARAM_NAMES: dict[type, list[str]] = {}


def _check_obs_fields(obs: Observation) -> None:
    """The Observation's fields still of the types it stored (O(1)): a field assigned after it
    was made (``obs.positions = "abc"``) fails here, naming it, not as an AttributeError inside a
    method."""
    for name, ndims in (("frames", (3,)), ("positions", (2, 3)), ("state0", (1,))):
        v = getattr(obs, name)
        if v is not None and not (isinstance(v, np.ndarray) and v.ndim in ndims
                                  and np.issubdtype(v.dtype, np.number)):
            raise ValueError(
                f"obs.{name}: expected a numeric array of {' or '.join(map(str, ndims))} "
                f"dimensions as Observation stores it, got {type(v).__name__} {str(v)[:40]!r} "
                "(changed after the Observation was made? build a new one)"
            )
    if not (isinstance(obs.dt, float) and DT_RANGE[0] <= obs.dt <= DT_RANGE[1]):
        raise ValueError(f"obs.dt: expected seconds in {DT_RANGE}, got {obs.dt!r} (changed after "
                         "the Observation was made? build a new one)")
    if obs.floor is not None and not (isinstance(obs.floor, float) and abs(obs.floor) <= FLOOR_MAX):
        raise ValueError(f"obs.floor: expected None or metres within +-{FLOOR_MAX:g}, got "
                         f"{obs.floor!r} (changed after the Observation was made? build a new one)")


def _check_train(train) -> None:
    """``fit``'s ``train``: None (keep the model as it is) or a ``sysid_bench.core.datasets.Dataset``."""
    # datasets sits above this module (it makes Observations), so it is not imported here: a
    # Dataset can only exist once its module is loaded, so the class is looked up there
    dataset_cls = getattr(sys.modules.get("sysid_bench.core.datasets"), "Dataset", None)
    if train is not None and not (dataset_cls is not None and isinstance(train, dataset_cls)):
        raise ValueError(
            f"train: expected None or a sysid_bench.core.datasets.Dataset (make_dataset / "
            f"load_dataset), got {type(train).__name__}"
        )


def _check_lengths(obs: Observation, lengths) -> list[int]:
    """``identify_prefixes``' ``lengths`` as ints in ``[1, obs.n_frames]``."""
    arr = check_int_array(np.atleast_1d(lengths), "lengths", lo=1, hi=obs.n_frames)
    return [int(n) for n in arr]


def _validating_init(init):
    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        init(self, *args, **kwargs)
        if type(self).__init__ is __init__:  # only once, after the most derived __init__
            self._validate()

    return __init__


def _checking_identify(identify):
    @functools.wraps(identify)
    def wrapper(self, obs, *args, **kwargs):
        _check_obs(obs, self)
        _check_obs_fields(obs)
        self._validate()
        return identify(_with_knowledge(self, obs), obs, *args, **kwargs)

    return wrapper


def _checking_fit(fit):
    @functools.wraps(fit)
    def wrapper(self, train=None, *args, **kwargs):
        _check_train(train)
        self._validate()
        return fit(self, train, *args, **kwargs)

    return wrapper


def _checking_prefixes(identify_prefixes):
    @functools.wraps(identify_prefixes)
    def wrapper(self, obs, lengths, *args, **kwargs):
        _check_obs(obs, self)
        _check_obs_fields(obs)
        lengths = _check_lengths(obs, lengths)
        self._validate()
        return identify_prefixes(_with_knowledge(self, obs), obs, lengths, *args, **kwargs)

    return wrapper


def _checking_forecast(forecast):
    @functools.wraps(forecast)
    def wrapper(self, obs, horizon, *args, **kwargs):
        _check_obs(obs, self)
        _check_obs_fields(obs)
        horizon = check_horizon(horizon, MAX_HORIZON)
        self._validate()
        return forecast(_with_knowledge(self, obs), obs, horizon, *args, **kwargs)

    return wrapper
