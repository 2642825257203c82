"""Training and validation data for Vid2Param: videos plus the normalised latent targets.

Targets are normalised to about [0, 1]: positions by the view (``x / 10``, ``(y - floor) / 10``),
parameters by ``PRIOR`` (``physics.normalise_theta``), velocities (if used) by 10 m/s to about
[-1, 1].

Data come from ``sysid_bench.core.datasets.make_dataset``: the ``train`` split (sub-ranges 0, 2, 4, 6,
8) for training, the ``test`` split for validation (with a seed other than the reported
evaluation's).
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core.datasets import make_dataset
from sysid_bench.core.physics import BOX_WIDTH, normalise_theta

__all__ = ["targets_from_dataset", "make_split", "rolls_mask", "chunk_seed", "perturb_dataset",
           "PointVideos", "make_system_split", "system_targets_from_arrays", "normalise_points"]

#: Velocities are divided by this (m/s) when used as targets.
VEL_SCALE = 10.0


def targets_from_arrays(states, theta, floor, names) -> np.ndarray:
    """Normalised targets for the supervised latent dimensions.

    Parameters
    ----------
    states : ndarray, shape (N, T, 4)
        ``[x, y, vx, vy]`` in metres and m/s.
    theta : ndarray, shape (N, T, 4) or (N, 4)
        Parameter labels in physical units.
    floor : ndarray, shape (N,)
        Floor height in metres.
    names : sequence of str
        Target names from ``model.TARGETS``.

    Returns
    -------
    ndarray, shape (N, T, K), float32
    """
    states = np.asarray(states, dtype=np.float64)
    n, t = states.shape[:2]
    th = np.asarray(theta, dtype=np.float64)
    if th.ndim == 2:
        th = np.broadcast_to(th[:, None, :], (n, t, 4))
    u = normalise_theta(th)
    fl = np.broadcast_to(np.asarray(floor, dtype=np.float64), (n,))
    cols = {
        "x": states[..., 0] / BOX_WIDTH,
        "y": (states[..., 1] - fl[:, None]) / BOX_WIDTH,
        "vx": states[..., 2] / VEL_SCALE,
        "vy": states[..., 3] / VEL_SCALE,
        "e": u[..., 0],
        "g": u[..., 1],
        "d": u[..., 2],
        "r": u[..., 3],
    }
    return np.stack([cols[k] for k in names], axis=-1).astype(np.float32)


def normalise_points(points, extent) -> np.ndarray:
    """Points (..., K, 2) in metres to the view's unit square: ``(x - x0) / (x1 - x0)``,
    ``(y - y0) / (y1 - y0)`` for ``extent = (x0, x1, y0, y1)``."""
    x0, x1, y0, y1 = (float(v) for v in extent)
    p = np.asarray(points, dtype=np.float64)
    return np.stack([(p[..., 0] - x0) / (x1 - x0), (p[..., 1] - y0) / (y1 - y0)], axis=-1)


def system_targets_from_arrays(system, points, theta, names) -> np.ndarray:
    """Normalised targets of a system's videos (not the ball's, ``targets_from_arrays``).

    Parameters
    ----------
    system : sysid_bench.core.systems.System
    points : ndarray, shape (N, T, K, 2)
        The tracked points, metres (``system.observe``).
    theta : ndarray, shape (N, P)
        Parameters in physical units.
    names : sequence of str
        Target names (``model.system_targets``): ``x, y, x1, y1, ...`` and parameter names.

    Returns
    -------
    ndarray, shape (N, T, len(names)), float32
        Positions in the view's unit square, parameters in the prior's ([0, 1]).
    """
    from methods.vid2param.model import position_names

    pts = normalise_points(points, system.extent)
    n, t, k = pts.shape[:3]
    u = system.normalise(np.asarray(theta, dtype=np.float64))
    cols = {name: pts[..., i // 2, i % 2] for i, name in enumerate(position_names(k))}
    cols.update({p: np.broadcast_to(u[:, None, j], (n, t)) for j, p in enumerate(system.params)})
    return np.stack([cols[k] for k in names], axis=-1).astype(np.float32)


class PointVideos:
    """Rendered videos of a system with what the network is supervised on: its K tracked
    points and P parameters (a ``presets.VIEW`` network's targets).

    Attributes
    ----------
    system : System
    frames : ndarray, shape (N, T, H, W), uint8
    states : ndarray, shape (N, T, S)
    theta : ndarray, shape (N, P)
    points : ndarray, shape (N, T, K, 2), metres
    """

    def __init__(self, system, frames, states, theta, points):
        self.system, self.frames, self.states = system, frames, states
        self.theta, self.points = theta, points

    def targets(self, names) -> np.ndarray:
        """Normalised targets (N, T, len(names)) (:func:`system_targets_from_arrays`)."""
        return system_targets_from_arrays(self.system, self.points, self.theta, names)


#: Videos per seeded part of a system's split (``make_system_split``).
PART = 50


def make_system_split(system, split: str, n: int, seed: int, n_frames: int = 200, size=None,
                      nuisance=None, dt: float = 0.05, workers: int = 1) -> PointVideos:
    """``n`` videos of a system's ``split`` (``System.sample_cases``, then ``simulate`` and
    ``render`` at ``size``, default the system's), all from ``seed``.

    Parameters
    ----------
    system : str or System
    split : {"train", "test"}
    n, seed, n_frames : int
    size : (int, int), optional
    nuisance : dict, optional
        Camera nuisances passed to ``render`` (their ``seed`` derived from ``seed``).
    workers : int
        Threads drawing the parts (``PART`` videos each, seeded ``(seed, part)``): the videos
        do not depend on it.
    """
    from concurrent.futures import ThreadPoolExecutor

    from sysid_bench.core import systems

    s = systems.get(system)
    if split not in ("train", "test"):
        raise ValueError(f"split: expected 'train' or 'test', got {split!r}")
    n = int(n)

    def part(k: int):
        # fixed parts of PART videos, each from (seed, k): the same videos whatever the workers
        rng = np.random.default_rng([int(seed), 7001, k])
        theta, state0 = s.sample_cases(min(PART, n - k * PART), rng, split)
        states = s.simulate(theta, state0, n_frames=int(n_frames), dt=dt)
        nuis = dict(nuisance or {})
        if nuis:
            nuis.setdefault("seed", int(rng.integers(2**62)))
        return theta, states, s.render(states, theta, size=size, **nuis)

    n_parts = -(-n // PART)
    w = max(1, min(int(workers), n_parts))
    if w == 1:
        parts = [part(k) for k in range(n_parts)]
    else:  # the renderers' array work releases the GIL: threads share a chunk's drawing
        with ThreadPoolExecutor(w) as pool:
            parts = list(pool.map(part, range(n_parts)))
    theta, states, frames = (np.concatenate(a) for a in zip(*parts))
    return PointVideos(s, frames, states, theta, s.observe(states, theta))


def targets_from_dataset(ds, names) -> np.ndarray:
    """Targets (N, T, K) from a ``sysid_bench.core.datasets.Dataset`` (uses its ``labels``) or a
    system's :class:`PointVideos`."""
    if isinstance(ds, PointVideos):
        return ds.targets(names)
    labels = getattr(ds, "labels", None)
    theta = labels if labels is not None else ds.theta
    return targets_from_arrays(ds.states, theta, ds.floor, names)


def rolls_mask(states, floor, min_frames: int = 5) -> np.ndarray:
    """Videos in which the ball rolls (on the floor, vy = 0, still moving) for some frames.

    ``r`` is only observable there. A ball that stops at once after its last hop gives no
    information on ``r``, hence ``min_frames`` of rolling with ``vx != 0``.

    Parameters
    ----------
    states : ndarray, shape (N, T, 4)
    floor : ndarray, shape (N,) or scalar

    Returns
    -------
    ndarray, shape (N,), bool
    """
    states = np.asarray(states, dtype=np.float64)
    fl = np.broadcast_to(np.asarray(floor, dtype=np.float64), states.shape[:1])
    on_floor = np.abs(states[..., 1] - fl[:, None]) < 1e-9
    rolling = on_floor & (states[..., 3] == 0.0) & (np.abs(states[..., 2]) > 1e-9)
    return rolling.sum(axis=1) >= min_frames


def chunk_seed(data_seed: int, k: int) -> int:
    """Seed of the ``k``-th fresh training chunk: distinct streams for distinct (seed, k)."""
    return int(np.random.SeedSequence([int(data_seed), int(k)]).generate_state(1)[0])


def make_split(split: str, n: int, seed: int, size=(28, 28), nuisance=None, n_frames: int = 200,
               variant: str = "interleaved", **variant_options):
    """One split (``sysid_bench.core.datasets.make_dataset``; the interleaved variant by default)."""
    return make_dataset(split, n, seed, variant=variant, n_frames=n_frames, size=tuple(size),
                        nuisance=nuisance, **variant_options)


def perturb_dataset(ds, spin: float, dwell: float, seed: int = 0, p: float = 1.0):
    """The cases of ``ds`` re-simulated with per-video deviations from our physics.

    A fraction ``p`` of the videos (each independently) draws a spin loss ``U(0, spin)`` and a
    contact dwell ``U(0, dwell)`` s and is re-simulated from its own parameters, initial state
    and floor with ``sysid_bench.core.physics.simulate_perturbed``, then rendered again with the
    dataset's own camera nuisances (fresh nuisance draws, from ``seed``); the others are kept
    byte for byte.

    Parameters
    ----------
    ds : Dataset
        Constant-parameter videos (not the ``changing`` variant).
    spin : float in [0, 1)
    dwell : float in [0, dt)
    seed : int
    p : float in [0, 1]

    Returns
    -------
    Dataset
        ``extras["spin"]``, ``extras["dwell"]`` (N,) hold each video's deviations (0 where
        kept); ``meta["perturbed"]`` records the arguments.
    """
    import dataclasses

    from sysid_bench.core.physics import simulate_perturbed
    from sysid_bench.core.render import render

    theta = np.asarray(ds.theta)
    if theta.ndim == 3 and not (theta == theta[:, :1]).all():
        raise ValueError("ds: expected constant parameters per video, got a changing variant")
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p: expected a probability in [0, 1], got {p!r}")
    rng = np.random.default_rng([int(seed), 99])
    n, t = ds.states.shape[:2]
    chosen = rng.random(n) < p
    sp = np.where(chosen, rng.uniform(0.0, spin, n), 0.0)
    dw = np.where(chosen, rng.uniform(0.0, dwell, n), 0.0)
    states = np.array(ds.states, copy=True)
    frames = np.array(ds.frames, copy=True)
    idx = np.flatnonzero(chosen)
    if idx.size:
        dt = float(ds.meta.get("dt", 0.05))
        states[idx] = simulate_perturbed(theta[idx, 0] if theta.ndim == 3 else theta[idx],
                                         states[idx, 0], spin=sp[idx], dwell=dw[idx], n_frames=t,
                                         dt=dt, floor=np.asarray(ds.floor)[idx])
        nuis = {k: v for k, v in (ds.meta.get("nuisance") or {}).items() if k != "floor_offset"}
        # as make_dataset: the camera is framed on floor 0 (a raised floor shows as a lifted ball)
        rngs = [np.random.default_rng([int(seed), 98, int(i)]) for i in idx]
        frames[idx] = render(states[idx], size=tuple(frames.shape[-2:]), floor=0.0, seed=rngs,
                             dt=dt, **nuis)
    meta = {**ds.meta, "perturbed": {"spin_max": spin, "dwell_max": dwell, "p": p, "seed": seed}}
    return dataclasses.replace(ds, frames=frames, states=states, meta=meta,
                               extras={**ds.extras, "spin": sp, "dwell": dw})
