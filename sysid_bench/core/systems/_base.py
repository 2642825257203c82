"""What the suite knows of one dynamical system: the :class:`System` base class.

A system is one module holding a subclass of :class:`System` (as sbibm's tasks hold prior,
simulator and observation together, and DeepMind's Hamiltonian suite has one module per
system). The subclass declares its parameters, prior, state, tracked points and default view as
class attributes, and implements five hooks:

``_simulate(theta, state0, n_frames, dt, scene=None)``
    The NumPy simulator: validated float64 ``theta`` (B, T, P) (parameters held from frame t to
    t+1) and ``state0`` (B, S) in, states (B, T, S) out, frame 0 = ``state0``, events located
    exactly. A subclass that sets ``_theta_row_ok = True`` gets constant parameters as
    (B, 1, P) instead, one row held for every frame (no (B, T, P) copy: ~5 ms at 2000 x 200). This is the one source of the system's physics. ``scene`` (an instance of
    :attr:`System.scene_type`, validated; see :mod:`sysid_bench.core.systems._scene`) is the geometry;
    a hook without the keyword is called without it, for the default scene only.
``sample_state0(n, rng, theta=None)``
    Initial states from the system's documented ranges. ``theta`` (n, P), optional, is the
    trajectories' parameters, for a system whose initial state is defined relative to a
    parameter (the spring's ``x0 = L0 + s0``); other systems ignore it (or omit the keyword:
    callers pass it only where the signature has it, see :meth:`System.sample_cases`).
``_observe(states, theta, scene=None)``
    States (B, T, S) to the K tracked points' positions (B, T, K, 2) in metres (in ``scene``).
``_render(points, states, theta, size, **nuisance)``
    Frames (B, T, H, W) uint8; most systems draw discs through :mod:`sysid_bench.core.systems._draw`.
``_track(frames)``
    Frames (T, H, W) to positions (T, K, 2), NaN where a point is not seen.

plus, for the reference checks and NUTS, ``reference(theta, state0, n_frames, dt)`` (an
event-driven ``scipy.integrate.solve_ivp`` at tight tolerance, one trajectory) and a JAX twin named
by ``jax_twin = "module:function"`` (imported only when asked for, so JAX loads only for NUTS).

A system may also override what the rest of the suite would otherwise ask of its name (issue
37: no branch on the ball's name outside its files): ``check_observation(obs,
default_scene)`` (an :class:`~sysid_bench.core.estimator.Observation`'s fields: the ball keeps its
(T, 2) positions, box and floor), ``track_observed(frames, floor)`` (the ball tracks above a
known floor), ``known_geometry`` and ``check_posterior_mean``.

The public methods validate at the boundary (shapes, empty batches, ragged lists, NaN/inf, the
documented envelope, the scene's type, frame sizes) and raise ``ValueError`` (``TypeError`` for
a scene of the wrong type) naming the argument and the system; the hooks receive clean arrays.
"""

from __future__ import annotations

import abc
import functools
import importlib
import inspect
from typing import ClassVar

import numpy as np

from sysid_bench.core._observation_checks import check_dt, check_in_view
from sysid_bench.core._validate import (
    as_float_array,
    check_batch,
    check_frame_budget,
    check_number,
    check_positive_int,
    check_seed,
)
from sysid_bench.core.systems._scene import Scene, check_within

__all__ = ["System", "Scene", "SUBRANGES_TRAIN", "SUBRANGES_TEST"]

#: The paper's leak-free interleaved split: each parameter's prior range is cut into 10 equal
#: sub-ranges numbered 0-9 from the low end; training draws from the even ones, testing from the
#: odd ones, so no test value is ever seen in training.
SUBRANGES_TRAIN = (0, 2, 4, 6, 8)
SUBRANGES_TEST = (1, 3, 5, 7, 9)

#: Accepted seconds between frames (as the ball's ``DT_RANGE``).
_DT_RANGE = (1e-4, 1.0)
#: Longest simulation accepted (frames); 100x a video.
_MAX_FRAMES = 20000


#: A batch of at least this many trajectories is simulated over numba's threads by the systems
#: whose kernels have a parallel twin (pendulum, spring); smaller ones (a method's few
#: simulations per step) stay serial, where starting the threads would cost more than it gains.
PARALLEL_MIN = 512


def use_parallel(batch: int) -> bool:
    """Whether a batch of ``batch`` trajectories takes the parallel kernel: large enough, and
    called from the main thread (numba's default threading layer does not take parallel
    launches from several threads at once; the training data is drawn by threads). The
    benchmark runner's workers get ``NUMBA_NUM_THREADS`` = their ``threads``."""
    import threading

    return batch >= PARALLEL_MIN and threading.current_thread() is threading.main_thread()


class System(abc.ABC):
    """A dynamical system seen by a camera.

    Class attributes
    ----------------
    name : str
        Registry name.
    params : tuple of str
        Parameter names: the order of ``theta`` and of every ``Posterior``.
    prior : dict of str -> (float, float)
        Uniform prior range of each parameter (also what splits and metrics are built from).
    envelope : dict of str -> (float, float)
        Values ``simulate`` accepts (at least the prior; wider where the physics allows it).
    state : tuple of str
        State variable names, the last axis of ``simulate``'s output.
    state_bounds : dict of str -> (float, float)
        Values ``simulate`` accepts for each state variable of ``state0``.
    n_points : int
        K, the number of tracked points ``observe`` and ``track`` return.
    extent : (float, float, float, float)
        ``(x0, x1, y0, y1)`` metres of the default camera's view.
    size : (int, int)
        Default frame size ``(H, W)``.
    noise_m : float
        Position noise (m) the benchmark adds for the position-input methods.
    jax_twin : str
        ``"module:function"`` of the JAX twin (``theta (P,), state0 (S,), n_frames, dt -> (T, S)``),
        or ``""`` when the system has none.
    scene_type : type
        The frozen dataclass of the system's geometry (:class:`Scene` or a subclass);
        ``scene_type()`` is the default scene (the design's numbers), see :meth:`scene`.
    min_size : (int, int)
        Smallest frames ``(H, W)`` that ``render`` draws and ``track`` reads: below it the
        object does not fit the frame (``track`` would answer NaN or noise).
    paper : str
        The publication whose claims the report compares this system's figures with (its
        readings go to the report's "differ from the paper" list), or ``""``.
    headline_groups : tuple of tuple of str
        Groups of parameters whose mean error the report's summary shows beside the overall
        one (e.g. the ball's r, unknowable until the ball rolls, apart from e, g, d).
    datasets : bool
        Whether the benchmark draws this system's test cases from :mod:`sysid_bench.core.datasets`
        (the paper's split generator, its render nuisances and variants: the ball's) instead
        of :func:`sysid_bench.bench.cases.system_cases`.

    Every public method validates its arguments here, once for all systems (a user's included):
    ``simulate``, ``observe``, ``render`` and ``track`` are defined on this class, and a
    subclass's ``sample_state0`` is wrapped on definition (:meth:`__init_subclass__`) so ``n``,
    ``rng`` and ``theta`` are checked before the system's own code runs.
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[str, ...]] = ()
    prior: ClassVar[dict[str, tuple[float, float]]] = {}
    envelope: ClassVar[dict[str, tuple[float, float]]] = {}
    state: ClassVar[tuple[str, ...]] = ()
    state_bounds: ClassVar[dict[str, tuple[float, float]]] = {}
    n_points: ClassVar[int] = 1
    extent: ClassVar[tuple[float, float, float, float]] = (0.0, 10.0, 0.0, 10.0)
    size: ClassVar[tuple[int, int]] = (28, 28)
    noise_m: ClassVar[float] = 0.01
    jax_twin: ClassVar[str] = ""
    scene_type: ClassVar[type[Scene]] = Scene
    min_size: ClassVar[tuple[int, int]] = (4, 4)
    paper: ClassVar[str] = ""
    headline_groups: ClassVar[tuple[tuple[str, ...], ...]] = ()
    datasets: ClassVar[bool] = False
    #: Whether ``_simulate`` takes constant parameters as (B, 1, P) (see the module docstring).
    _theta_row_ok: ClassVar[bool] = False
    #: Experiment 3 (changing parameters): the parameters that jump (None: every one); each is
    #: re-drawn from its test sub-ranges every ``every`` frames (:meth:`changing_theta`).
    changing_params: ClassVar[tuple[str, ...] | None] = None
    #: The :mod:`sysid_bench.core.datasets` variant that holds this system's own changing-parameter
    #: test videos ("": none, the bench simulates them from :meth:`changing_theta`).
    changing_dataset: ClassVar[str] = ""
    #: True where :mod:`sysid_bench.core.datasets` makes this system's training sets for every
    #: sensitivity condition (extrapolation, label noise, simplified physics) as videos of the
    #: paper's split (the ball), so experiment 4 can train condition models in the run. Every
    #: system draws the conditions' parameters through :meth:`sample_variant`.
    sensitivity_training: ClassVar[bool] = False
    #: The parameters held at one value in the sensitivity experiment's "simplified physics"
    #: training (the ball's drag and rolling; a system's dissipation and nonlinear terms): each
    #: at 45% of its prior range, the centre of training sub-range 4 (:meth:`sample_variant`).
    #: Empty: the system has no simplified condition.
    simplified_params: ClassVar[tuple[str, ...]] = ()
    #: Experiment 5's cases off the system's own physics, beside its test cases: ``"perturbed"``
    #: (test cases re-simulated by physics that is not ours, with its own render) and
    #: ``"meaningless"`` (clips no physics explains). Both are made from the paper's datasets
    #: and :func:`sysid_bench.core.physics.simulate_perturbed`, so a system declares them only with
    #: :attr:`datasets` (the ball); every system gets its own test cases.
    calibration_conditions: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        conds = tuple(cls.calibration_conditions)
        if set(conds) - {"perturbed", "meaningless"} or (conds and not cls.datasets):
            raise TypeError(f"{cls.__name__}.calibration_conditions: expected a subset of "
                            "('perturbed', 'meaningless'), declared only with datasets = True, "
                            f"got {conds!r} (datasets = {cls.datasets!r})")
        if cls.params and set(cls.simplified_params) - set(cls.params):
            raise TypeError(f"{cls.__name__}.simplified_params: expected names among "
                            f"{cls.params}, got {cls.simplified_params!r}")
        fn = cls.__dict__.get("sample_state0")
        if fn is not None and not getattr(fn, "_checked", False):
            cls.sample_state0 = _checked_sample_state0(fn)

    # ------------------------------------------------------------------------------------------
    # the prior
    @property
    def n_params(self) -> int:
        """P, the number of parameters."""
        return len(self.params)

    @property
    def n_state(self) -> int:
        """S, the length of the state."""
        return len(self.state)

    @property
    def prior_lo(self) -> np.ndarray:
        """Lower prior bounds, shape (P,)."""
        return np.array([self.prior[p][0] for p in self.params], dtype=np.float64)

    @property
    def prior_hi(self) -> np.ndarray:
        """Upper prior bounds, shape (P,)."""
        return np.array([self.prior[p][1] for p in self.params], dtype=np.float64)

    def normalise(self, theta) -> np.ndarray:
        """Parameters (..., P) mapped to [0, 1] by the prior."""
        lo, hi = self.prior_lo, self.prior_hi
        return (np.asarray(theta, dtype=np.float64) - lo) / (hi - lo)

    def denormalise(self, u) -> np.ndarray:
        """Inverse of :meth:`normalise`."""
        lo, hi = self.prior_lo, self.prior_hi
        return lo + np.asarray(u, dtype=np.float64) * (hi - lo)

    def subrange_bounds(self, param: str, k: int) -> tuple[float, float]:
        """Bounds of sub-range ``k`` (0-9 from the low end) of ``param``'s prior range."""
        if param not in self.params:
            raise ValueError(f"param: expected one of {self.params} ({self.name}), got {param!r}")
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k <= 9:
            raise ValueError(f"k: expected an integer sub-range in 0..9, got {k!r}")
        lo, hi = self.prior[param]
        w = (hi - lo) / 10.0
        return lo + k * w, lo + (k + 1) * w

    def sample_theta(self, n: int, rng=None, split: str | None = None) -> np.ndarray:
        """Parameters drawn uniformly from the prior, or from one side of the interleaved split.

        Parameters
        ----------
        n : int
        rng : int, None or numpy.random.Generator
        split : {None, "train", "test"}
            ``"train"`` draws each parameter from the even tenths of its range, ``"test"`` from
            the odd ones (:data:`SUBRANGES_TRAIN`, :data:`SUBRANGES_TEST`); ``None`` from all.

        Returns
        -------
        ndarray, shape (n, P)
        """
        n = check_positive_int(n, "n")
        rng = check_seed(rng)
        p = self.n_params
        if split is None:
            u = rng.random((n, p))
        elif split in ("train", "test"):
            sub = np.asarray(SUBRANGES_TRAIN if split == "train" else SUBRANGES_TEST)
            k = rng.choice(sub, size=(n, p))
            u = (k + rng.random((n, p))) / 10.0
        else:
            raise ValueError(f"split: expected None, 'train' or 'test', got {split!r}")
        return self.denormalise(u)

    def changing_theta(self, n: int, n_frames: int, every: int, rng=None) -> np.ndarray:
        """Piecewise-constant parameters for experiment 3: a test draw per case, then every
        ``every`` frames the :attr:`changing_params` re-drawn from their test sub-ranges.

        Parameters
        ----------
        n, n_frames, every : int
        rng : int, None or numpy.random.Generator

        Returns
        -------
        ndarray, shape (n, n_frames, P)
            ``theta[:, t]`` holds from frame t to frame t+1 (as :meth:`simulate` takes it).
        """
        n = check_positive_int(n, "n")
        n_frames = check_positive_int(n_frames, "n_frames")
        every = check_positive_int(every, "every")
        rng = check_seed(rng)
        names = self.params if self.changing_params is None else self.changing_params
        bad = sorted(set(names) - set(self.params))
        if bad:
            raise ValueError(f"changing_params: expected names among {self.params} "
                             f"({self.name}), got {bad}")
        moving = np.isin(np.asarray(self.params), np.asarray(names))
        n_seg = -(-n_frames // every)
        seg = self.sample_theta(n * n_seg, rng, "test").reshape(n, n_seg, self.n_params)
        seg[:, 1:, ~moving] = seg[:, :1, ~moving]  # the fixed ones keep the first draw
        return np.repeat(seg, every, axis=1)[:, :n_frames]

    #: The sensitivity conditions' parameter draws (:meth:`sample_variant`) and their options.
    VARIANTS: ClassVar[dict[str, dict]] = {
        "interleaved": {}, "extrapolation": {"param": None, "fraction": 0.5},
        "noisy": {"label_noise": 0.05}, "simplified": {}}

    def sample_variant(self, n: int, rng=None, split: str = "train",
                       variant: str = "interleaved", **options):
        """Cases of one sensitivity condition (the paper's variants, as the ball's datasets):

        ``"interleaved"``   :meth:`sample_cases` of ``split``.
        ``"extrapolation"`` option ``param`` (required) and ``fraction`` (default 0.5): in
                            ``"train"`` that parameter is uniform on the lowest ``fraction`` of
                            its range, in ``"test"`` uniform above it; the others interleaved.
        ``"noisy"``         as interleaved; in ``"train"`` the labels get Gaussian noise of
                            ``label_noise`` (default 0.05) x each parameter's range, the
                            simulated ``theta`` stays true.
        ``"simplified"``    in ``"train"`` the :attr:`simplified_params` held at 45% of their
                            range; in ``"test"`` the full model, interleaved.

        One Generator, in a fixed order: same seed, same arrays.

        Parameters
        ----------
        n : int
        rng : int, None or numpy.random.Generator
        split : {"train", "test"}
        variant : str
            One of :attr:`VARIANTS`.

        Returns
        -------
        theta : ndarray, shape (n, P)
            The simulated parameters.
        labels : ndarray, shape (n, P)
            What training is told (``theta`` except for ``"noisy"`` training).
        state0 : ndarray, shape (n, S)
        distance : ndarray, shape (n,)
            ``"extrapolation"``: the value's signed distance from the training range's upper
            end in fractions of the prior range (<= 0 in train, in ``[0, 1 - fraction]`` in
            test); 0 otherwise.

        Raises
        ------
        ValueError
            An unknown ``split``, ``variant`` or option, a ``param`` that is not the system's,
            a ``fraction`` outside (0, 1), a ``label_noise`` outside [0, 1], or
            ``"simplified"`` on a system without :attr:`simplified_params`.
        """
        n = check_positive_int(n, "n")
        rng = check_seed(rng)
        if split not in ("train", "test"):
            raise ValueError(f"split: expected 'train' or 'test', got {split!r}")
        if variant not in self.VARIANTS:
            raise ValueError(f"variant: expected one of {tuple(self.VARIANTS)}, got {variant!r}")
        bad = sorted(set(options) - set(self.VARIANTS[variant]))
        if bad:
            raise ValueError(f"options: variant {variant!r} takes "
                             f"{sorted(self.VARIANTS[variant]) or 'no options'}, got {bad}")
        opts = {**self.VARIANTS[variant], **options}
        train = split == "train"
        theta = self.sample_theta(n, rng, split)
        distance = np.zeros(n)
        labels = theta
        if variant == "extrapolation":
            if opts["param"] not in self.params:
                raise ValueError(f"param: expected one of {self.params} ({self.name}), got "
                                 f"{opts['param']!r}")
            f = opts["fraction"]
            if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 1:
                raise ValueError(f"fraction: expected a number in (0, 1), got {f!r}")
            j = self.params.index(opts["param"])
            u = rng.random(n)
            frac = f * u if train else f + (1.0 - f) * u
            theta[:, j] = self.prior_lo[j] + frac * (self.prior_hi[j] - self.prior_lo[j])
            distance = frac - f
        elif variant == "simplified":
            if not self.simplified_params:
                raise ValueError(f"variant: the {self.name} system declares no simplified_params, "
                                 "so it has no 'simplified' condition")
            if train:
                for p in self.simplified_params:
                    j = self.params.index(p)
                    theta[:, j] = self.prior_lo[j] + 0.45 * (self.prior_hi[j] - self.prior_lo[j])
        elif variant == "noisy":
            s = opts["label_noise"]
            if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 <= s <= 1:
                raise ValueError(f"label_noise: expected a fraction of the range in [0, 1], "
                                 f"got {s!r}")
        state0 = self._state0_for(n, rng, theta)
        if variant == "noisy" and train and opts["label_noise"] > 0:
            # drawn last: the trajectories are the clean condition's, only the labels move
            labels = theta + rng.normal(0.0, opts["label_noise"] * (self.prior_hi - self.prior_lo),
                                        theta.shape)
        return theta, labels, state0, distance

    # ------------------------------------------------------------------------------------------
    # validation at the public boundary
    def check_theta(self, theta, n_frames: int | None = None, name: str = "theta") -> np.ndarray:
        """Validate parameters: float64 (B, P) or (B, n_frames, P), B >= 1, inside :attr:`envelope`."""
        p = self.n_params
        arr = _as_array(theta, name)
        if getattr(arr, "ndim", 0) in (2, 3) and arr.shape[-1] != p:
            raise ValueError(
                f"{name}: expected the {self.name} system's {p} parameters {self.params} on the "
                f"last axis, got shape {arr.shape}"
            )
        th = as_float_array(arr, name, ndim=(2, 3), last=p)
        check_batch(th, name, f"the {self.name} system's parameters")
        if th.ndim == 3 and n_frames is not None and th.shape[1] != n_frames:
            raise ValueError(
                f"{name}: expected (B, n_frames={n_frames}, {p}) for time-varying parameters of "
                f"the {self.name} system, got shape {th.shape}"
            )
        flat = th.reshape(-1, p)
        lo, hi = flat.min(axis=0), flat.max(axis=0)
        for i, q in enumerate(self.params):
            a, b = self.envelope.get(q, self.prior[q])
            if lo[i] < a or hi[i] > b:
                raise ValueError(
                    f"{name}: expected {q} in [{a:g}, {b:g}] for the {self.name} system "
                    f"(its envelope), got values in [{lo[i]:g}, {hi[i]:g}]"
                )
        return th

    def check_state0(self, state0, name: str = "state0", scene: Scene | None = None) -> np.ndarray:
        """Validate initial states: float64 (B, S), B >= 1, inside :meth:`state_bounds_for`
        ``(scene)`` (:attr:`state_bounds` for the default scene)."""
        s = self.n_state
        arr = _as_array(state0, name)
        if getattr(arr, "ndim", 0) == 2 and arr.shape[-1] != s:
            raise ValueError(
                f"{name}: expected the {self.name} system's state {self.state} ({s} values) on "
                f"the last axis, got shape {arr.shape}"
            )
        s0 = as_float_array(arr, name, ndim=2, last=s)
        check_batch(s0, name, f"the {self.name} system's initial states")
        sc = self.check_scene(scene)
        bounds = self.state_bounds_for(sc)
        for i, q in enumerate(self.state):
            if q not in bounds:
                continue
            a, b = bounds[q]
            col = s0[:, i]
            if col.size and (col.min() < a or col.max() > b):
                raise ValueError(
                    f"{name}: expected {q} in [{a:g}, {b:g}] for the {self.name} system"
                    f"{'' if sc == self.default_scene else ' in this scene'}, "
                    f"got values in [{col.min():g}, {col.max():g}]"
                )
        if _takes(self._check_state0_extra, "scene"):
            self._check_state0_extra(s0, name, scene=sc)
        else:
            self._check_state0_extra(s0, name)
        return s0

    # ------------------------------------------------------------------------------------------
    # the scene
    @property
    def default_scene(self) -> Scene:
        """The design's geometry: ``scene_type()``."""
        return self.scene_type()

    def scene(self, **overrides) -> Scene:
        """The system's scene with ``overrides`` (its fields by name), e.g.
        ``get("ball").scene(walls=None, floor=0.3)``; no overrides gives :attr:`default_scene`.

        Raises ``ValueError`` naming a field the scene does not have or a value it cannot hold.
        """
        return self.default_scene.replace(**overrides)

    def check_scene(self, scene, name: str = "scene") -> Scene:
        """``scene`` validated for this system: None is :attr:`default_scene`; else an instance
        of :attr:`scene_type` with finite values (``TypeError`` for another system's scene)."""
        if scene is None:
            return self.default_scene
        if not isinstance(scene, self.scene_type):
            other = getattr(scene, "system", "")
            got = (f"the {other} system's {type(scene).__name__}" if isinstance(scene, Scene) and other
                   else f"{type(scene).__name__} {scene!r}"[:200])
            raise TypeError(
                f"{name}: expected a {self.scene_type.__name__} for the {self.name} system "
                f"(systems.get({self.name!r}).scene(...)) or None, got {got}"
            )
        vals = scene.values()
        if not np.isfinite(vals).all():  # only reachable past the constructor (object.__setattr__)
            raise ValueError(f"{name}: expected finite metres in the {self.name} system's scene, got {scene!r}")
        return scene

    def state_bounds_for(self, scene: Scene) -> dict[str, tuple[float, float]]:
        """The bounds of ``state0`` in ``scene`` (a system whose state is in world metres shifts
        them with its geometry); :attr:`state_bounds` by default."""
        return self.state_bounds

    def _check_state0_extra(self, state0: np.ndarray, name: str) -> None:
        """Checks beyond per-variable bounds (e.g. an ordering); raise ``ValueError``."""
        return None  # none by default

    @staticmethod
    def _check_frames_dt(n_frames, dt) -> tuple[int, float]:
        n = check_positive_int(n_frames, "n_frames")
        if n > _MAX_FRAMES:
            raise ValueError(f"n_frames: expected at most {_MAX_FRAMES}, got {n}")
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
            raise ValueError(f"dt: expected a number of seconds, got {dt!r}")
        d = float(dt)
        if not np.isfinite(d) or not _DT_RANGE[0] <= d <= _DT_RANGE[1]:
            raise ValueError(f"dt: expected seconds in [{_DT_RANGE[0]:g}, {_DT_RANGE[1]:g}], got {dt!r}")
        return n, d

    # ------------------------------------------------------------------------------------------
    # the public API
    def simulate(self, theta, state0, n_frames: int = 200, dt: float = 0.05,
                 scene: Scene | None = None) -> np.ndarray:
        """Simulate a batch of trajectories.

        Parameters
        ----------
        theta : ndarray, shape (B, P) or (B, n_frames, P)
            Parameters in :attr:`params` order; a time-varying ``theta[:, t]`` holds from frame
            t to frame t+1. B >= 1.
        state0 : ndarray, shape (B, S)
        n_frames : int
        dt : float
            Seconds between frames.
        scene : Scene, optional
            The geometry (an instance of :attr:`scene_type`, see :meth:`scene`); None is
            :attr:`default_scene`, which gives the design's numbers bit for bit.

        Returns
        -------
        ndarray, shape (B, n_frames, S)
            States at the frame times; frame 0 is ``state0``.
        """
        n_frames, dt = self._check_frames_dt(n_frames, dt)
        sc = self.check_scene(scene)
        th = self.check_theta(theta, n_frames)
        s0 = self.check_state0(state0, scene=sc)
        if th.shape[0] != s0.shape[0]:
            raise ValueError(
                f"state0: expected one row per theta row ({th.shape[0]}), got {s0.shape[0]}"
            )
        if th.ndim == 2:
            th = th[:, None, :] if self._theta_row_ok else np.broadcast_to(
                th[:, None, :], (th.shape[0], n_frames, th.shape[1]))
        args = (np.ascontiguousarray(th), np.ascontiguousarray(s0), n_frames, dt)
        out = self._call_hook(self._simulate, args, sc, "simulate")
        if not np.isfinite(out).all():
            raise RuntimeError(f"{self.name}: the simulation produced non-finite states")
        return out

    def observe(self, states, theta, scene: Scene | None = None) -> np.ndarray:
        """Positions of the K tracked points, shape (B, T, K, 2), metres, from states (B, T, S)
        in ``scene`` (None = :attr:`default_scene`)."""
        st = as_float_array(_as_array(states, "states"), "states", ndim=3, last=self.n_state,
                            allow_nan=True)
        th = self.check_theta(theta)
        if th.shape[0] != st.shape[0]:
            raise ValueError(f"theta: expected one row per video ({st.shape[0]}), got {th.shape[0]}")
        return self._call_hook(self._observe, (st, th), self.check_scene(scene), "observe")

    def _call_hook(self, hook, args, scene: Scene, what: str):
        """``hook(*args, scene=scene)`` where the hook takes a scene; a hook written without one
        (a user's system) is called without it, for the default scene only."""
        if _takes(hook, "scene"):
            return hook(*args, scene=scene)
        if scene != self.default_scene:
            raise ValueError(f"scene: the {self.name} system's {what} takes no scene (its _{what} "
                             f"hook has no scene argument), got {scene!r}")
        return hook(*args)

    def render(self, states, theta, size=None, **nuisance) -> np.ndarray:
        """Frames (B, T, H, W) uint8 of states (B, T, S); nuisances as :func:`_draw.finish`.

        ``size`` (H, W) must be at least :attr:`min_size` (the object must fit) and the frames
        at most :data:`sysid_bench.core._validate.FRAME_BUDGET` pixels in all; both are refused
        before anything is allocated.
        """
        st = as_float_array(_as_array(states, "states"), "states", ndim=3, last=self.n_state)
        th = self.check_theta(theta)
        if th.shape[0] != st.shape[0]:
            raise ValueError(f"theta: expected one row per video ({st.shape[0]}), got {th.shape[0]}")
        from sysid_bench.core.render import check_size

        size = self.size if size is None else check_size(size)
        self._check_min_size(size, "size")
        check_frame_budget((st.shape[0], st.shape[1]) + tuple(size), "size")
        return self._render(self._observe(st, th), st, th, size, **nuisance)

    def _check_min_size(self, hw, name: str) -> None:
        mh, mw = self.min_size
        if hw[0] < mh or hw[1] < mw:
            raise ValueError(
                f"{name}: expected frames of at least {mh} x {mw} pixels (H x W) for the "
                f"{self.name} system (smaller ones cannot hold its object), got {hw[0]} x {hw[1]}"
            )

    def track(self, frames) -> np.ndarray:
        """Positions (T, K, 2) in metres of the K tracked points in frames (T, H, W); NaN = unseen.

        Frames smaller than :attr:`min_size` are refused (the object cannot be in them)."""
        fr = _as_array(frames, "frames")
        if fr.ndim != 3:
            raise ValueError(f"frames: expected a (T, H, W) array, got shape {fr.shape}")
        if fr.shape[0] == 0:
            raise ValueError(f"frames: expected at least one frame, got shape {fr.shape}")
        self._check_min_size(fr.shape[1:], "frames")
        if fr.dtype != np.uint8:
            fr = as_float_array(fr, "frames", ndim=3)
            if fr.size and (fr.min() < 0 or fr.max() > 255):
                raise ValueError(
                    f"frames: expected values in [0, 255], got [{fr.min():g}, {fr.max():g}]"
                )
        return self._track(fr)

    def track_observed(self, frames, floor: float | None = None) -> np.ndarray:
        """Positions (T, K, 2) tracked in frames (T, H, W) of an observation that may know a
        ``floor`` (m; an :class:`~sysid_bench.core.estimator.Observation` field, None: unknown).
        Here :meth:`track`: only the ball has a floor to track above
        (:class:`~sysid_bench.core.systems.ball.Ball`)."""
        return self.track(frames)

    def jax_simulate(self):
        """The JAX twin: ``f(theta (P,), state0 (S,), n_frames, dt) -> (T, S)`` (imports JAX)."""
        if not self.jax_twin:
            raise NotImplementedError(f"the {self.name} system has no JAX twin")
        module, fn = self.jax_twin.split(":")
        return getattr(importlib.import_module(module), fn)

    def state0_from_track(self, positions, dt: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Where a position-only method starts: a rough initial state from a track.

        Parameters
        ----------
        positions : ndarray, shape (T, K, 2)
            Observed points in metres, NaN where unseen (noise of a few cm).
        dt : float

        Returns
        -------
        state0 : ndarray, shape (S,)
            Estimate of the state at frame 0 (inside :attr:`state_bounds`).
        scale : ndarray, shape (S,)
            Half-width of a box around it that holds the true state0 with high probability.
        """
        raise NotImplementedError(f"the {self.name} system gives no initial state from a track")

    #: How far (in prior widths, per parameter) a posterior mean may lie outside
    #: :attr:`envelope`: an unclipped network or an unbounded fit can put a mean a little past a
    #: bound, and the posterior is a result that says so; a mean several widths out is no
    #: statement about the system, and is refused where it is made.
    mean_margin: ClassVar[float] = 1.0

    def check_posterior_mean(self, mean: np.ndarray) -> None:
        """``ValueError`` naming ``mean`` when a parameter of the posterior mean ``mean`` (P,)
        lies more than :attr:`mean_margin` prior widths outside :attr:`envelope`."""
        for q, m, (lo, hi) in zip(self.params, mean, self._mean_bounds()):
            if not lo <= m <= hi:
                a, b = self.envelope.get(q, self.prior[q])
                raise ValueError(
                    f"mean: expected {q} within {self.mean_margin:g} prior width of the "
                    f"physical envelope [{a:g}, {b:g}] ({self.name}.envelope), i.e. in "
                    f"[{lo:.4g}, {hi:.4g}], got {q} = {m:g}")

    def _mean_bounds(self) -> list[tuple[float, float]]:
        """Per parameter, the range :meth:`check_posterior_mean` accepts (hook)."""
        out = []
        for q in self.params:
            a, b = self.envelope.get(q, self.prior[q])
            pad = self.mean_margin * (self.prior[q][1] - self.prior[q][0])
            out.append((a - pad, b + pad))
        return out

    def known_geometry(self, scene: Scene | None = None) -> dict:
        """Fields of an :class:`~sysid_bench.core.estimator.Observation` beyond ``scene`` that say
        the scene's geometry is known (none for most systems: the scene says it all; the
        ball's floor is a field of its own). How the harness hands every system's cases to
        a method with the geometry known, the same for all."""
        return {}

    def check_observation(self, obs, default_scene: bool) -> None:
        """Check the fields of an :class:`~sysid_bench.core.estimator.Observation` of this system
        and store them normalised on ``obs`` (its frames, system name and scene are checked
        already). Here: positions (T, K, 2) ((T, 2) read as K = 1) near the view (in a scene
        other than the default, within the scenes' reach), ``dt`` in ``DT_RANGE``, ``floor`` a
        number, ``state0`` (S,) through :meth:`check_state0`. The ball keeps its own (T, 2),
        box and floor (:class:`~sysid_bench.core.systems.ball.Ball`).

        Raises
        ------
        ValueError
            A field of the wrong shape or out of range, naming it.
        """
        if obs.positions is not None:
            pos = as_float_array(obs.positions, "positions", ndim=(2, 3), last=2, allow_nan=True)
            if pos.ndim == 2:
                pos = pos[:, None, :]
            if pos.shape[1] != self.n_points:
                raise ValueError(
                    f"positions: expected (T, {self.n_points}, 2) for the {self.name} system's "
                    f"{self.n_points} tracked points, got shape {pos.shape}"
                )
            if pos.shape[0] < 1:
                raise ValueError("positions: expected at least 1 frame, got 0")
            if obs.frames is not None and obs.frames.shape[0] != pos.shape[0]:
                raise ValueError(
                    "positions: expected as many rows as frames "
                    f"({obs.frames.shape[0]}), got {pos.shape[0]}"
                )
            if default_scene:
                check_in_view(pos.reshape(-1, 2), self, "positions")
            else:  # the scene moves the world: only a wrong unit can still be caught
                check_within(pos.reshape(-1, 2), "positions")
            obs.positions = pos
        obs.dt = check_dt(obs.dt)
        if obs.floor is not None:
            obs.floor = check_number(obs.floor, "floor", unit="m")
        if obs.state0 is not None:
            s0 = as_float_array(obs.state0, "state0", ndim=1, last=self.n_state)
            obs.state0 = self.check_state0(s0[None], "state0", scene=obs.scene)[0]

    def reference(self, theta, state0, n_frames: int = 200, dt: float = 0.05) -> np.ndarray:
        """Event-driven ``solve_ivp`` reference of one trajectory: (P,), (S,) -> (n_frames, S)."""
        raise NotImplementedError(f"the {self.name} system has no solve_ivp reference")

    # ------------------------------------------------------------------------------------------
    # hooks
    @abc.abstractmethod
    def _simulate(self, theta: np.ndarray, state0: np.ndarray, n_frames: int, dt: float) -> np.ndarray:
        """Validated (B, T, P) and (B, S) to states (B, T, S)."""

    @abc.abstractmethod
    def sample_state0(self, n: int, rng=None, theta=None) -> np.ndarray:
        """Initial states (n, S) from the system's documented ranges; ``theta`` (n, P), optional,
        the trajectories' parameters, where the initial state depends on them."""

    def sample_cases(self, n: int, rng=None, split: str | None = None):
        """Parameters (n, P) from :meth:`sample_theta`, then initial states (n, S) for them.

        One Generator, in that order; ``theta`` goes to :meth:`sample_state0` where its signature
        takes it (a subclass written before the keyword existed still works).

        Parameters
        ----------
        n : int
        rng : int, None or numpy.random.Generator
        split : {None, "train", "test"}
            As :meth:`sample_theta`.

        Returns
        -------
        theta : ndarray, shape (n, P)
        state0 : ndarray, shape (n, S)
        """
        rng = check_seed(rng)
        theta = self.sample_theta(n, rng, split)
        return theta, self._state0_for(n, rng, theta)

    def _state0_for(self, n: int, rng, theta: np.ndarray) -> np.ndarray:
        """:meth:`sample_state0` for ``theta``, passed where its signature takes it (a subclass
        written before the keyword existed still works)."""
        if "theta" in inspect.signature(self.sample_state0).parameters:
            return self.sample_state0(n, rng, theta=theta)
        return self.sample_state0(n, rng)

    @abc.abstractmethod
    def _observe(self, states: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """States (B, T, S) and theta (B, P) to points (B, T, K, 2)."""

    @abc.abstractmethod
    def _render(self, points, states, theta, size, **nuisance) -> np.ndarray:
        """Points (B, T, K, 2) (and states, theta) to frames (B, T, H, W) uint8."""

    @abc.abstractmethod
    def _track(self, frames: np.ndarray) -> np.ndarray:
        """Frames (T, H, W) to points (T, K, 2), NaN where unseen."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, params={self.params}, K={self.n_points})"


def _as_array(value, name: str):
    """``np.asarray(value)``, a ragged or unconvertible value answered naming ``name``."""
    if isinstance(value, np.ndarray):
        return value
    try:
        return np.asarray(value)
    except (ValueError, TypeError):
        raise ValueError(f"{name}: expected a rectangular numeric array, got a ragged or "
                         f"non-numeric {type(value).__name__}") from None


def _takes(fn, arg: str) -> bool:
    try:
        return arg in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _checked_sample_state0(fn):
    """``sample_state0`` with its arguments checked first (n >= 1; rng a seed >= 0, None or a
    Generator; theta, where given, (n, P) finite and inside the envelope), for every system."""

    @functools.wraps(fn)
    def sample_state0(self, n, rng=None, *args, **kwargs):
        n = check_positive_int(n, "n")
        rng = check_seed(rng, "rng")
        theta = kwargs.get("theta", args[0] if args else None)
        if theta is not None:
            th = self.check_theta(theta, name="theta")
            if th.shape != (n, self.n_params):
                raise ValueError(f"theta: expected shape ({n}, {self.n_params}) (one row per "
                                 f"initial state of the {self.name} system), got {th.shape}")
        return fn(self, n, rng, *args, **kwargs)

    sample_state0._checked = True
    return sample_state0
