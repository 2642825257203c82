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
    if type(value) is np.ndarray and value.dtype == np.float64:
        arr = value  # already what the checks of the dtype below make (a stream's every push)
    else:
        try:
            arr = np.asarray(value)
        except Exception as exc:  # ragged lists and the like
            raise ValueError(f"{name}: expected a numeric array, got {type(value).__name__} "
                             f"({exc})") from exc
        if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
            # bool arrays too: True/False read as 1/0 metres or parameters is a mask passed
            # where values belong, never a measurement
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


def _is_real(value) -> bool:
    """A real number that is not a bool (``True`` is an int to Python, never a number here) and
    not a string (``float("0.05")`` works, but a string is a value nobody parsed). A 0-d NumPy
    array of a real dtype (a scalar read from an ``.npz``) is a number."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return value.dtype != np.bool_ and (np.issubdtype(value.dtype, np.integer)
                                            or np.issubdtype(value.dtype, np.floating))
    return (not isinstance(value, (bool, np.bool_))
            and isinstance(value, (int, float, np.integer, np.floating)))


def check_positive_float(value, name: str) -> float:
    """Return ``value`` as float, raising unless it is a real number (not str, not bool),
    finite and > 0."""
    if not _is_real(value):
        raise ValueError(f"{name}: expected a positive number, got {type(value).__name__} {value!r}")
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


def check_int(value, name: str, *, lo: int | None = None, hi: int | None = None) -> int:
    """``value`` as an int in ``[lo, hi]``; floats (even ``2.0``), strings and bools are refused."""
    rng = ("" if lo is None and hi is None else
           f" in [{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer{rng}, got {type(value).__name__} {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ValueError(f"{name}: expected an integer{rng}, got {value}")
    return int(value)


def check_int_array(value, name: str, *, lo: int | None = None, hi: int | None = None,
                    ndim: int = 1) -> np.ndarray:
    """``value`` as an int64 array of ``ndim`` dimensions with values in ``[lo, hi]``.

    Integer-valued floats are refused like any float (``[0.5]`` and ``[2.0]`` alike): an index
    list that arrives as floats was computed, and its rounding is the caller's to decide.
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists
        raise ValueError(f"{name}: expected integers, got {type(value).__name__} ({exc})") from exc
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected integers, got dtype {arr.dtype} ({value!r})")
    if arr.ndim != ndim:
        raise ValueError(f"{name}: expected a {ndim}-D sequence of integers, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name}: expected at least one integer, got none")
    if (lo is not None and arr.min() < lo) or (hi is not None and arr.max() > hi):
        rng = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
        raise ValueError(f"{name}: expected integers in {rng}, got values in "
                         f"[{arr.min()}, {arr.max()}]")
    return arr.astype(np.int64)


def check_flag(value, name: str) -> bool:
    """``value`` as a bool; only ``True``/``False`` (and NumPy's) are flags.

    ``bool("no")`` is True, so a string taken as a flag would silently mean the opposite of
    what it says: strings, numbers and None are refused.
    """
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {type(value).__name__} {value!r}")
    return bool(value)


def check_seed(seed, name: str = "seed") -> np.random.Generator:
    """Turn an int seed >= 0, ``None`` or a Generator into a Generator (``name`` is the
    argument's name in the message: ``rng`` where the caller calls it that)."""
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None:
        return np.random.default_rng(seed)
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, (bool, np.bool_)):
        if seed < 0:  # NumPy's own answer ("expected non-negative integer") names nothing
            raise ValueError(f"{name}: expected a seed >= 0, None or numpy.random.Generator, got {seed}")
        return np.random.default_rng(seed)
    raise ValueError(f"{name}: expected an int seed >= 0, None or numpy.random.Generator, "
                     f"got {type(seed).__name__} {seed!r}")


def check_batch(arr: np.ndarray, name: str, what: str = "rows") -> None:
    """Refuse an empty batch (``arr.shape[0] == 0``) naming ``name``: a (0, P) array is nearly
    always a filter that kept nothing, and NumPy would answer it later with a reduction error."""
    if arr.ndim == 0 or arr.shape[0] == 0:
        raise ValueError(f"{name}: expected a batch of at least one row of {what}, got an empty "
                         f"batch of shape {arr.shape}")


#: Most pixels a call may ask to draw in all (B x T x H x W): 2**30 is 1 GiB of uint8 frames and
#: 4 GiB of the float32 the drawing works in. A size beyond it is almost always a typo
#: ((100000, 100000) asked for 186 GiB) and is refused before anything is allocated.
FRAME_BUDGET = 2**30
#: Longest side of one frame, pixels.
SIDE_MAX = 2**14


def check_frame_budget(shape, name: str = "size") -> None:
    """Refuse frames of ``shape`` (B, T, H, W) whose drawing would need more than
    :data:`FRAME_BUDGET` pixels, or a side above :data:`SIDE_MAX`, naming ``name``."""
    b, t, h, w = (int(v) for v in shape)
    if max(h, w) > SIDE_MAX:
        raise ValueError(f"{name}: expected frames of at most {SIDE_MAX} pixels a side, got {h} x {w}")
    total = b * t * h * w
    if total > FRAME_BUDGET:
        raise ValueError(
            f"{name}: expected at most 2**30 pixels to draw in all ({FRAME_BUDGET * 5 / 2**30:.0f} "
            f"GiB with the float32 drawing), got {b} x {t} frames of {h} x {w} = {total:.3g} "
            f"pixels; draw fewer or smaller frames, or in batches"
        )


def check_number(value, name: str, *, lo: float | None = None, hi: float | None = None,
                 unit: str = "") -> float:
    """``value`` as a finite float within ``[lo, hi]``; strings and bools are refused.

    A string such as ``"0.05"`` would be converted by ``float`` but is almost always a file or
    command-line value nobody parsed, so it is named instead of silently accepted.
    """
    u = f" {unit}" if unit else ""
    rng = ("" if lo is None and hi is None else
           f" in [{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]{u}")
    if not _is_real(value):
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
            f"(sysid_bench.core.estimator.MAX_HORIZON), got {horizon}"
        )
    return int(horizon)


#: Largest hyperparameter seed: NumPy takes any, but JAX keys and torch generators take 32 or 64
#: bits, and a seed that only some methods accept is a value one boundary takes and another
#: refuses (2**70 reached numpyro as an ``OverflowError``).
SEED_MAX = 2**32 - 1


def check_seed_value(seed, name: str = "seed", *, generator: bool = True):
    """A hyperparameter seed, returned as is: an int in ``[0, SEED_MAX]``, None or (where the
    method can use one, ``generator=True``) a ``numpy.random.Generator``."""
    if seed is None or (generator and isinstance(seed, np.random.Generator)):
        return seed
    what = f"an int in [0, 2**32 - 1]{', None or numpy.random.Generator' if generator else ' or None'}"
    if (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))
            or not 0 <= seed <= SEED_MAX):
        raise ValueError(f"{name}: expected {what}, got {type(seed).__name__} {seed!r}")
    return seed


def check_annotated(value, name: str, annotation) -> None:
    """Check a hyperparameter against its constructor annotation (a string, as
    ``from __future__ import annotations`` leaves them): ``bool`` a flag, ``int`` an integer,
    ``float`` a real number, ``str`` a string, each optionally ``| None``.

    Ranges are each method's own (its ``_validate``); this is the type every method shares, so a
    new method's ``sigma='0.02'`` or ``progress='no'`` is refused without a line of its own.
    Other annotations (or none) are not checked here.
    """
    ann = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    parts = [a.strip() for a in ann.split("|")]
    if "None" in parts:
        if value is None:
            return
        parts.remove("None")
    if len(parts) != 1:
        return
    kind = parts[0]
    if kind == "bool":
        check_flag(value, name)
    elif kind == "int":
        check_int(value, name)
    elif kind == "float":
        check_number(value, name)
    elif kind == "str" and not isinstance(value, str):
        raise ValueError(f"{name}: expected a string, got {type(value).__name__} {value!r}")


def arg_number(lo: float | None = None, hi: float | None = None, *, integer: bool = False,
               lo_open: bool = False, unit: str = ""):
    """An ``argparse`` ``type=`` function: a finite number (an integer with ``integer=True``)
    in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), else ``argparse.ArgumentTypeError`` naming
    the range, which argparse prints as one line with the option's name and exits 2.
    """
    import argparse

    u = f" {unit}" if unit else ""
    left = "(" if lo_open else "["
    rng = f"{left}{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]{u}"
    what = "an integer" if integer else "a finite number"

    def parse(text: str):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} in {rng}, got {text!r}") from None
        if (not np.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo))
                or (hi is not None and v > hi)):
            raise argparse.ArgumentTypeError(f"expected {what} in {rng}, got {text!r}")
        return v

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in errors
    return parse
