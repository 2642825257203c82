"""Scales of a benchmark run and the test cases every method sees.

Cases come from :func:`sysid_bench.core.datasets.make_dataset` on the **test** split with the run's
seed, so they are a pure function of (variant, options, seed): every worker, local or on a Dask
cluster, regenerates the same bytes (a few hundred ms per set, cached per process) instead of
shipping arrays around. Because a dataset of n videos is a prefix of one of more videos, a run
that asks for more cases later extends the earlier ones instead of replacing them.

Inputs
------
``video``       the frames and the floor height (what Vid2Param gets; position methods go
                through :mod:`sysid_bench.core.tracking`). The floor is given because the simulated
                test videos, like Vid2Param's training videos, all have the floor at the bottom
                of the view: a learned method knows it implicitly, and leaving position methods
                to guess it made them forecast bounces on the lowest point seen so far.
``privileged``  true positions and the true initial state, floor known, no frames (what the
                paper's lsq / bo baselines got). Only for methods that take positions.
"""

from __future__ import annotations

import difflib
import zlib
from dataclasses import asdict, dataclass, field
from functools import lru_cache

import numpy as np

from sysid_bench.core.estimator import Observation

__all__ = ["INPUTS", "Scale", "SCALES", "get_scale", "test_set", "train_set", "observation",
           "inputs_for", "unknown_name", "system_cases", "system_case", "N_FRAMES", "bench_case",
           "extended_case", "variant_cases", "variant_case"]

INPUTS = ("video", "privileged")
#: Bump when what a cell computes changes meaning (inputs, metrics): part of the grid config, so
#: a store computed under an older protocol is refused instead of mixed with new cells.
#: 3: per-method caps, options and tiers moved from the scale to the methods' declarations.
#: 4: every cell names its system (the store's ``system`` column).
PROTOCOL = 4


def unknown_name(kind: str, name, known) -> ValueError:
    """A ValueError listing the ``known`` names, with the closest match when there is one."""
    known = list(known)
    close = difflib.get_close_matches(str(name), known, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return ValueError(f"{kind}: unknown {kind} {name!r}; known: {', '.join(known)}.{hint}")


@dataclass(frozen=True)
class Scale:
    """How big a run is.

    Attributes
    ----------
    name : str
    seed : int
        Seed of every test (and sensitivity training) set.
    n_cases : dict
        Test cases per experiment (``identification``, ``forecasting``, ``changing``,
        ``sensitivity``, ``calibration``, ...): an int for every system, or a dict of
        system name to int with ``"*"`` for the systems not named (a user's too), since what
        keeps a figure stable within its CI differs between systems (:meth:`n_for`).
    lengths : tuple of int
        Observed frames of experiment 1.
    forecast_after, horizon : tuple of int, int
        Experiment 2: forecast the ``horizon`` frames after each of these prefix lengths.
    change_every, changing_stride : int, int
        Experiment 3: parameters change every ``change_every`` frames; methods without a
        streaming ``identify_prefixes`` are evaluated every ``changing_stride`` frames
        (streaming ones every frame).
    calibration_lengths : tuple of int
    calibration_inputs : tuple of str
    thin_expensive : bool
        Methods of the expensive tier (their class declares ``cost >= EXPENSIVE_COST``:
        samplers, Bayesian optimisation) are evaluated in experiment 1 at
        ``expensive_lengths`` only, in experiment 3 every ``expensive_stride`` frames and in
        experiment 5 at the longest of ``calibration_lengths``, so a run fits its time budget.
    expensive_lengths : tuple of int
    expensive_stride : int
    sensitivity : dict
        Experiment 4 (its test videos: ``n_cases["sensitivity"]``): ``n_train`` training
        videos of ``n_frames`` frames per condition, ``extrapolation`` parameters (``"all"``, a
        count or names: :meth:`sensitivity_conditions`), ``label_noise`` levels, ``simplified`` (bool), ``lengths``. The training budget is the
        method's own declaration (``fit_options`` per scale).
    online : (int, int)
        Experiment 7: frames per video and the stride of the every-prefix methods' timed
        prefixes (its test videos: ``n_cases["online"]``).

    What differs per method (case caps, hyperparameters, threads, cost tier) is declared on the
    method's class and read through :func:`methods.spec`; a scale holds no table of methods.
    """

    name: str
    seed: int = 2024
    n_cases: dict = field(default_factory=dict)
    lengths: tuple = tuple(range(10, 201, 10))
    forecast_after: tuple = (20, 50, 100)
    horizon: int = 100
    change_every: int = 50
    changing_stride: int = 10
    calibration_lengths: tuple = (50, 100, 200)
    calibration_inputs: tuple = ("video",)
    thin_expensive: bool = True
    expensive_lengths: tuple = (20, 50, 100, 150, 200)
    expensive_stride: int = 25
    sensitivity: dict = field(default_factory=dict)
    online: tuple = (200, 10)
    #: the scale whose per-method declarations (case caps, options, training budgets, ready
    #: models) and per-experiment settings apply (None: this scale's own name): ``quick`` is the
    #: default's methods on fewer cases
    declarations: str | None = None

    @property
    def declared_as(self) -> str:
        """The scale name the methods' per-scale declarations are read under when a method
        declares nothing for this scale itself (:meth:`key_for`)."""
        return self.declarations or self.name

    def key_for(self, per_scale) -> str:
        """The key of a method's per-scale declaration ``per_scale`` (``scale_cases``,
        ``scale_options``, ...) that applies here: this scale's own name where the method
        declares it, else :attr:`declared_as`."""
        return self.name if self.name in per_scale else self.declared_as

    def thinned(self, method: str) -> bool:
        """True when ``method`` is of the expensive tier and this scale thins those."""
        import methods

        return self.thin_expensive and methods.spec(method).expensive

    def lengths_for(self, method: str) -> tuple:
        """Observed-frame counts of experiment 1 for ``method``."""
        return self.expensive_lengths if self.thinned(method) else self.lengths

    def calibration_lengths_for(self, method: str) -> tuple:
        """Frame counts of experiment 5 for ``method``: expensive ones only the longest."""
        if self.thinned(method):
            return (max(self.calibration_lengths),)
        return self.calibration_lengths

    def stride_for(self, method: str) -> int:
        """Frames between estimates in experiment 3 for a non-streaming ``method``."""
        return self.expensive_stride if self.thinned(method) else self.changing_stride

    def n_for(self, experiment: str, system: str = "ball") -> int:
        """Test cases of ``experiment`` on ``system`` before any method's cap (the size of the
        case set the cells draw from)."""
        n = self.n_cases[experiment]
        if isinstance(n, dict):
            n = n.get(system, n.get("*", 0))
        return int(n)

    def cases(self, experiment: str, method: str, system: str = "ball") -> int:
        """Number of test cases ``method`` gets in ``experiment`` on ``system`` (its
        ``scale_cases`` cap)."""
        import methods

        n = self.n_for(experiment, system)
        spec = methods.spec(method)
        cap = spec.cases_cap(self.key_for(spec.scale_cases), experiment)
        return n if cap is None else min(n, cap)

    def method_options(self, method: str, threads: int | None = 1) -> dict:
        """Hyperparameters ``method`` gets at this scale (its ``scale_options``, and ``threads``
        for the one it declares as ``threads_param``)."""
        import methods

        spec = methods.spec(method)
        return spec.options(self.key_for(spec.scale_options), threads)

    def sensitivity_conditions(self, system: str = "ball") -> list[str]:
        """The sensitivity experiment's training conditions of ``system`` at this scale, e.g.
        ``["extrapolation:e", "noise:0", "noise:0.5", "simplified"]``.

        The scale's ``extrapolation`` entry is ``"all"`` (each of the system's parameters), a
        count (its first ones) or parameter names; ``simplified`` counts only for a system that
        declares ``simplified_params``."""
        from sysid_bench.core import systems

        sens = self.sensitivity
        s = systems.get(system)
        ex = sens.get("extrapolation", ())
        if ex == "all":
            ex = s.params
        elif isinstance(ex, int) and not isinstance(ex, bool):
            ex = s.params[:ex]
        out = [f"extrapolation:{p}" for p in ex]
        out += [f"noise:{float(x):g}" for x in sens.get("label_noise", ())]
        if sens.get("simplified") and s.simplified_params:
            out.append("simplified")
        return out

    def fit_options(self, method: str) -> dict:
        """Training hyperparameters of ``method`` in the sensitivity experiment at this scale."""
        import methods

        spec = methods.spec(method)
        return spec.training_options(self.key_for(spec.fit_options))

    def grid_config(self) -> dict:
        """What decides the cases and the numbers of a cell (case counts excluded: prefixes).

        A store refuses to mix cells computed under another grid config. What a method declares
        (options, caps, tier) is part of that method's fingerprint instead
        (:func:`sysid_bench.bench.fingerprint.method_fingerprint`).
        """
        d = asdict(self)
        for k in ("n_cases", "name"):
            d.pop(k)
        d["protocol"] = PROTOCOL
        # tuples -> lists so a JSON round trip compares equal
        return _jsonable(d)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


# Default-scale sensitivity: every condition of the paper, tested at up to 50 frames. A method
# that declares ready-trained condition models (``pretrained``) is evaluated on them; one that
# does not is trained here with ``n_train`` videos and its declared ``fit_options`` budget.
_SENS_SMALL = {
    "n_train": 400,
    "n_frames": 50,
    "extrapolation": "all",
    "label_noise": (0.0, 0.1, 0.25, 0.5),
    "simplified": True,
    "lengths": (10, 25, 50),
}

SCALES: dict[str, Scale] = {
    # seconds: for tests and CI
    "smoke": Scale(
        name="smoke",
        seed=7,
        n_cases={"identification": 2, "forecasting": 2, "changing": 1, "sensitivity": 2,
                 "calibration": 2, "systems": 1, "online": 1, "interception": 3,
                 "camera": 1},
        # expensive methods declare one case and a small budget here (smoke numbers mean nothing)
        lengths=(20, 60, 100),
        forecast_after=(20, 50),
        horizon=30,
        changing_stride=25,
        online=(60, 5),
        calibration_lengths=(50, 100),
        expensive_lengths=(50, 100),
        expensive_stride=50,
        sensitivity={
            "n_train": 16,
            "n_frames": 50,
            "extrapolation": 1,
            "label_noise": (0.0, 0.5),
            "simplified": True,
            "lengths": (25, 50),
        },
    ),
    # the first look: every section on every system, the default's methods on a few cases
    "quick": Scale(
        name="quick",
        declarations="default",
        n_cases={"identification": 2, "forecasting": 2, "changing": 1, "sensitivity": 5,
                 "calibration": 1, "systems": 1, "online": 1, "interception": 1,
                 "camera": 1},
        lengths=(20, 50, 100, 200),
        forecast_after=(50,),
        changing_stride=25,
        expensive_lengths=(50, 200),
        expensive_stride=50,
        calibration_lengths=(200,),
        sensitivity={**_SENS_SMALL, "lengths": (25, 50)},
        online=(100, 20),
    ),
    # <= 15 min on 2 cores with the shipped Vid2Param checkpoint (measured in the report)
    "default": Scale(
        name="default",
        n_cases={"identification": {"ball": 20, "*": 4}, "forecasting": {"ball": 20, "*": 4},
                 # changing on the other systems: see sysid_bench/bench/changing.py (cost)
                 "changing": {"ball": 10, "*": 3}, "sensitivity": 50,
                 # calibration on the other systems: 4 cases (nuts, the reference, on 3: its
                 # cap), as identification there; the ball's perturbed and meaningless clips
                 # come on top (sysid_bench/bench/calibration.py)
                 "calibration": {"ball": 20, "*": 4}, "systems": 10, "online": 2,
                 "interception": 40,
                 # camera footage: 3 clips per system (360p), filmed once per run
                 "camera": 3},
        # Measured seconds per cell, one worker at low load (a full default grid without
        # vid2param summed to 690 core-seconds): lsq 0.5-3.4, sindy 0.3-1.4, bo 4-13,
        # emcee 9-25, nuts ~25 per posterior (~100 under a load of 5). The expensive ones declare
        # caps (the first cases only, the same cases as everyone); nuts, the reference
        # posterior, only in experiment 5. `--scale paper` runs every method on every case.
        expensive_lengths=(20, 50, 100, 200),
        expensive_stride=50,
        calibration_lengths=(50, 200),
        sensitivity=_SENS_SMALL,
    ),
    # the paper's sizes: 100 test videos, 10,000 training videos per sensitivity model
    "paper": Scale(
        name="paper",
        n_cases={"identification": 100, "forecasting": 100, "changing": 100, "sensitivity": 100,
                 "calibration": 100, "systems": 100, "online": 5, "interception": 200,
                 "camera": 20},
        thin_expensive=False,
        changing_stride=1,
        online=(200, 1),
        calibration_inputs=("video", "privileged"),
        sensitivity={
            "n_train": 10_000,
            "n_frames": 200,
            "extrapolation": "all",
            "label_noise": (0.0, 0.1, 0.2, 0.3, 0.4, 0.5),
            "simplified": True,
            "lengths": tuple(range(10, 201, 10)),
        },
    ),
}


def get_scale(name: str | Scale) -> Scale:
    """The scale called ``name`` (a Scale passes through)."""
    if isinstance(name, Scale):
        return name
    if name not in SCALES:
        raise unknown_name("scale", name, SCALES)
    return SCALES[name]


@lru_cache(maxsize=16)
def _dataset(split: str, variant: str, n: int, seed: int, options: tuple):
    from sysid_bench.core.datasets import make_dataset

    ds = make_dataset(split, n, seed, variant=variant, **dict(options))
    # cached per worker process and shared by its cells: read-only (as a loaded dataset's
    # memory maps are), so no cell can change the videos of the cells after it (issue 37)
    for a in (ds.frames, ds.states, ds.theta, ds.labels, ds.floor, *ds.extras.values()):
        if isinstance(a, np.ndarray):
            a.setflags(write=False)
    return ds


def test_set(variant: str, n: int, seed: int, **options):
    """The first ``n`` test videos of ``variant`` (cached per process).

    Returns
    -------
    sysid_bench.core.datasets.Dataset
    """
    return _dataset("test", variant, int(n), int(seed), tuple(sorted(options.items())))


def train_set(variant: str, n: int, seed: int, **options):
    """Training videos of ``variant`` (not cached: only sensitivity training uses them once)."""
    from sysid_bench.core.datasets import make_dataset

    return make_dataset("train", int(n), int(seed), variant=variant, **options)


def observation(ds, i: int, input: str) -> Observation:
    """Test video ``i`` of ``ds`` as the ``input`` kind (see the module docstring)."""
    if input == "video":
        return Observation(frames=np.asarray(ds.frames[i]), dt=float(ds.meta["dt"]),
                           floor=float(ds.floor[i]))
    if input == "privileged":
        full = ds.observation(i, positions=True, state0=True)
        return Observation(positions=full.positions, dt=full.dt, floor=full.floor,
                           state0=full.state0)
    raise unknown_name("input", input, INPUTS)


def inputs_for(input_kind: str, wanted=INPUTS) -> list[str]:
    """Inputs a method of ``input_kind`` ("frames" or "positions") is run on."""
    if input_kind == "frames":
        return [i for i in wanted if i == "video"]
    return list(wanted)


#: Frames of a system's test case (the design's 200 at dt = 0.05).
N_FRAMES = 200


@lru_cache(maxsize=16)
def system_cases(system: str, n: int, seed: int, stream: int = 0):
    """The first ``n`` test-split cases of ``system`` (cached per process, read-only).

    Parameters from the odd tenths of each prior range, initial states from the system's own
    ranges, one random stream per system fixed by ``seed`` and the system's name; noise of
    ``system.noise_m`` on the tracked points. ``stream`` > 0: another, independent set of the
    same distribution (:func:`extended_case`: cases beyond a set another experiment drew).

    Returns
    -------
    theta : ndarray, shape (n, P)
    states : ndarray, shape (n, T, S)
    points : ndarray, shape (n, T, K, 2)
        The true tracked points.
    noisy : ndarray, shape (n, T, K, 2)
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    # one stream per system, fixed by the scale's seed and the system's name
    key = [seed, zlib.crc32(system.encode())]
    rng = np.random.default_rng(key + [int(stream)] if stream else key)
    theta = sys_.sample_theta(n, rng, "test")
    try:
        state0 = sys_.sample_state0(n, rng, theta=theta)
    except TypeError:  # systems whose initial state does not depend on theta
        state0 = sys_.sample_state0(n, rng)
    states = sys_.simulate(theta, state0, n_frames=N_FRAMES)
    points = sys_.observe(states, theta)
    noisy = points + rng.normal(0.0, sys_.noise_m, points.shape)
    # cached per process and handed out as views: read-only, so a method that wrote into its
    # observation cannot change the cases of the cells a worker runs after it (issue 37)
    for a in (theta, states, points, noisy):
        a.setflags(write=False)
    return theta, states, points, noisy


def system_case(system: str, i: int, n: int, seed: int, input_kind: str, stream: int = 0):
    """Case ``i`` of :func:`system_cases` (of its set ``stream``) as an observation of
    ``input_kind``.

    ``"video"``: the system's own render (seeded by the case); ``"positions"``: the noisy
    tracked points, no initial state; ``"privileged"``: the true points and the true initial
    state (the paper's privileged baselines). The scene's geometry is known in each
    (:meth:`System.observation`).

    Returns
    -------
    obs : Observation
        All ``N_FRAMES`` frames.
    theta : ndarray, shape (P,)
    points : ndarray, shape (T, K, 2)
        The true tracked points.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    theta, states, points, noisy = system_cases(system, n, seed, stream)
    known = {"system": sys_.name, **sys_.known_geometry()}
    if input_kind == "video":
        frames = sys_.render(states[i : i + 1], theta[i : i + 1],
                             seed=[seed, i, stream] if stream else [seed, i])[0]
        obs = Observation(frames=frames, **known)
    elif input_kind == "positions":
        obs = Observation(positions=noisy[i], **known)
    elif input_kind == "privileged":
        obs = Observation(positions=points[i], state0=states[i, 0], **known)
    else:
        raise unknown_name("input", input_kind, ("video", "positions", "privileged"))
    return obs, theta[i], points[i]


def bench_case(system: str, i: int, n: int, seed: int, input_kind: str,
               variant: str = "interleaved"):
    """Test case ``i`` of ``n`` of ``system`` as the ``input_kind`` observation, wherever the
    system's cases come from: :mod:`sysid_bench.core.datasets`' ``variant`` test set for a system
    that declares ``datasets`` (the ball: the paper's split, nuisances and variants), else
    :func:`system_case`.

    Returns
    -------
    obs : Observation
    theta : ndarray, shape (P,)
        The truth (at frame 0).
    points : ndarray, shape (T, K, 2)
        The true tracked points.
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    if sys_.datasets:
        ds = test_set(variant, n, seed)
        obs = observation(ds, i, input_kind)
        return obs, np.asarray(ds.theta[i, 0]), np.asarray(ds.states[i, :, None, :2])
    return system_case(sys_.name, i, n, seed, input_kind)


def extended_case(system: str, i: int, n: int, n_shared: int, seed: int, input_kind: str,
                  variant: str = "interleaved"):
    """Case ``i`` of ``n`` test cases of ``system`` whose first ``n_shared`` are
    :func:`bench_case`'s of a set of ``n_shared`` (the cases calibration, identification and
    forecasting draw: the same bytes, so the fits of a method that declares ``pure_fit`` are
    shared with them, :mod:`sysid_bench.bench.fitcache`), the others further test cases.

    A system's set of ``n`` cases is not the first ``n_shared`` of a larger one (its random
    stream draws every parameter, then every initial state), so the cases past ``n_shared``
    come from an independent stream of the same test distribution (:func:`system_cases`,
    ``stream=1``); a system that declares ``datasets`` (the ball), whose sets are prefixes of
    larger ones, gives case ``i`` of its set of ``n``.

    Returns
    -------
    obs : Observation
    theta : ndarray, shape (P,)
    points : ndarray, shape (T, K, 2)
        The true tracked points.
    """
    from sysid_bench.core import systems

    for name, v in (("i", i), ("n", n), ("n_shared", n_shared)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"{name}: expected an int >= 0, got {v!r}")
    if not i < n:
        raise ValueError(f"i: expected a case in [0, {n}), got {i!r}")
    if i < n_shared:
        return bench_case(system, i, n_shared, seed, input_kind, variant)
    sys_ = systems.get(system)
    if sys_.datasets:
        return bench_case(system, i, n, seed, input_kind, variant)
    return system_case(sys_.name, i - n_shared, n - n_shared, seed, input_kind, stream=1)


@lru_cache(maxsize=16)
def changing_cases(system: str, n: int, seed: int, every: int):
    """The first ``n`` changing-parameter test cases of ``system`` (experiment 3; cached per
    process, read-only).

    Parameters from :meth:`System.changing_theta` (the system declares which jump), initial
    states for the first frame's parameters, one random stream per system fixed by ``seed``
    and the system's name, ``N_FRAMES`` frames.

    Returns
    -------
    theta : ndarray, shape (n, T, P)
        The parameters in force at each frame.
    states : ndarray, shape (n, T, S)
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    rng = np.random.default_rng([seed, zlib.crc32(f"changing/{system}".encode())])
    theta = sys_.changing_theta(n, N_FRAMES, every, rng)
    try:
        state0 = sys_.sample_state0(n, rng, theta=theta[:, 0])
    except TypeError:  # systems whose initial state does not depend on theta
        state0 = sys_.sample_state0(n, rng)
    states = sys_.simulate(theta, state0, n_frames=N_FRAMES)
    for a in (theta, states):
        a.setflags(write=False)
    return theta, states


def changing_case(system: str, i: int, n: int, seed: int, every: int):
    """Case ``i`` of :func:`changing_cases` as a video observation (the system's own render,
    seeded by the case; the scene's geometry known).

    Returns
    -------
    obs : Observation
    theta : ndarray, shape (T, P)
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    theta, states = changing_cases(system, n, seed, every)
    frames = sys_.render(states[i : i + 1], theta[i : i + 1], seed=[seed, i])[0]
    return Observation(frames=frames, system=sys_.name, **sys_.known_geometry()), theta[i]


@lru_cache(maxsize=16)
def variant_cases(system: str, variant: str, n: int, seed: int, n_frames: int,
                  options: tuple = ()):
    """The first ``n`` test cases of one sensitivity condition of ``system``
    (:meth:`System.sample_variant` on the ``"test"`` side; cached per process, read-only).

    One random stream per (system, variant, options), fixed by ``seed``.

    Returns
    -------
    theta : ndarray, shape (n, P)
    states : ndarray, shape (n, n_frames, S)
    distance : ndarray, shape (n,)
        Extrapolation: the value's distance above the training range (fraction of the range).
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    key = [seed, zlib.crc32(system.encode()), zlib.crc32(f"{variant}{options}".encode())]
    rng = np.random.default_rng(key)
    theta, _, state0, distance = sys_.sample_variant(n, rng, "test", variant, **dict(options))
    states = sys_.simulate(theta, state0, n_frames=int(n_frames))
    for a in (theta, states, distance):
        a.setflags(write=False)
    return theta, states, distance


def variant_case(system: str, i: int, n: int, seed: int, n_frames: int, variant: str,
                 **options) -> tuple[Observation, np.ndarray, float]:
    """Case ``i`` of :func:`variant_cases` as a video observation (the system's own render,
    seeded by the case; the scene's geometry known).

    Returns
    -------
    obs : Observation
    theta : ndarray, shape (P,)
    distance : float
    """
    from sysid_bench.core import systems

    sys_ = systems.get(system)
    opts = tuple(sorted(options.items()))
    theta, states, distance = variant_cases(system, variant, n, seed, n_frames, opts)
    frames = sys_.render(states[i : i + 1], theta[i : i + 1],
                         seed=[seed, i, zlib.crc32(f"{variant}{opts}".encode())])[0]
    obs = Observation(frames=frames, system=sys_.name, **sys_.known_geometry())
    return obs, theta[i], float(distance[i])
