"""Argument checks shared by the public functions.

Every check raises ``ValueError`` whose message names the argument, what was expected and what
came, so a user sees at once which input to fix.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _describe(a: np.ndarray) -> str:
    return f"shape {a.shape} dtype {a.dtype}"


def as_float_array(
    value,
    name: str,
    *,
    ndim: int | Sequence[int] | None = None,
    last: int | None = None,
    allow_nan: bool = False,
) -> np.ndarray:
    """Convert ``value`` to a float64 array and check its rank, last axis and finiteness.

    Parameters
    ----------
    value : array_like
    name : str
        Argument name used in error messages.
    ndim : int or sequence of int, optional
        Accepted numbers of dimensions.
    last : int, optional
        Required length of the last axis.
    allow_nan : bool
        NaN marks missing values where True; inf is never allowed.
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name}: expected a numeric array, got {type(value).__name__} ({exc})") from exc
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.bool_)
    ):
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise ValueError(f"{name}: expected a real array, got complex dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if ndim is not None:
        dims = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in dims:
            want = " or ".join(f"{d}-D" for d in dims)
            raise ValueError(f"{name}: expected a {want} array, got {_describe(arr)}")
    if last is not None and (arr.ndim == 0 or arr.shape[-1] != last):
        raise ValueError(f"{name}: expected last axis of length {last}, got {_describe(arr)}")
    if allow_nan:
        if np.isinf(arr).any():
            raise ValueError(f"{name}: expected finite values or NaN, got inf")
    elif not np.isfinite(arr).all():
        bad = "NaN" if np.isnan(arr).any() else "inf"
        raise ValueError(f"{name}: expected finite values, got {bad}")
    return arr


def check_positive_int(value, name: str, *, minimum: int = 1) -> int:
    """Return ``value`` as int, raising if it is not an integer >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value}")
    return int(value)


def check_positive_float(value, name: str) -> float:
    """Return ``value`` as float, raising unless it is finite and > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a positive number, got {value!r}") from exc
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


def check_seed(seed) -> np.random.Generator:
    """Turn an int seed, ``None`` or a Generator into a Generator."""
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None or isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        return np.random.default_rng(seed)
    raise ValueError(f"seed: expected an int, None or numpy.random.Generator, got {seed!r}")


def check_number(value, name: str, *, lo: float | None = None, hi: float | None = None,
                 unit: str = "") -> float:
    """``value`` as a finite float within ``[lo, hi]``; strings and bools are refused.

    A string such as ``"0.05"`` would be converted by ``float`` but is almost always a file or
    command-line value nobody parsed, so it is named instead of silently accepted.
    """
    u = f" {unit}" if unit else ""
    rng = ("" if lo is None and hi is None else
           f" in [{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]{u}")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a real number{rng}, got {type(value).__name__} {value!r}")
    v = float(value)
    if not np.isfinite(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{name}: expected a finite number{rng}, got {value!r}")
    return v


def check_horizon(horizon, maximum: int) -> int:
    """``horizon`` as an int in ``[1, maximum]`` frames, else ``ValueError`` naming it."""
    if isinstance(horizon, (bool, np.bool_)) or not isinstance(horizon, (int, np.integer)):
        raise ValueError(f"horizon: expected an integer number of frames in [1, {maximum}], got {horizon!r}")
    if not 1 <= horizon <= maximum:
        raise ValueError(
            f"horizon: expected an integer number of frames in [1, {maximum}] "
            f"(sysid_bench.estimator.MAX_HORIZON), got {horizon}"
        )
    return int(horizon)


def check_seed_value(seed, name: str = "seed"):
    """A hyperparameter seed: an int >= 0, None or a ``numpy.random.Generator``; returned as is."""
    if seed is None or isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{name}: expected an int >= 0, None or numpy.random.Generator, got {seed!r}")
    return seed
