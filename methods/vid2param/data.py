"""Training and validation data for Vid2Param: videos plus the normalised latent targets.

Targets are normalised to about [0, 1]: positions by the view (``x / 10``, ``(y - floor) / 10``),
parameters by ``PRIOR`` (``physics.normalise_theta``), velocities (if used) by 10 m/s to about
[-1, 1].

Data come from ``sysid_bench.datasets.make_dataset``: the ``train`` split (sub-ranges 0, 2, 4, 6,
8) for training, the ``test`` split for validation (with a seed other than the reported
evaluation's).
"""

from __future__ import annotations

import numpy as np

from sysid_bench.datasets import make_dataset
from sysid_bench.physics import BOX_WIDTH, normalise_theta

__all__ = ["targets_from_dataset", "make_split", "rolls_mask", "chunk_seed"]

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


def targets_from_dataset(ds, names) -> np.ndarray:
    """Targets (N, T, K) from a ``sysid_bench.datasets.Dataset`` (uses its ``labels``)."""
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


def make_split(split: str, n: int, seed: int, size=(28, 28), nuisance=None, n_frames: int = 200):
    """One split of the interleaved variant (``sysid_bench.datasets.make_dataset``)."""
    return make_dataset(split, n, seed, n_frames=n_frames, size=tuple(size), nuisance=nuisance)
