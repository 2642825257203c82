"""Seeded, leak-free splits of bouncing-ball videos, in memory or written to disk in chunks.

Splits (design.md, paper Setup section)
---------------------------------------
Each parameter's range (``physics.PRIOR``) is cut into 10 equal sub-ranges numbered 0-9 from the
low end. Variants:

``"interleaved"``
    train draws each parameter from sub-ranges ``SUBRANGES_TRAIN`` (0, 2, 4, 6, 8), test from
    ``SUBRANGES_TEST`` (1, 3, 5, 7, 9): each parameter independently picks a sub-range, then a
    value uniformly inside it.
``"changing"``
    as interleaved, but the parameters are re-drawn every ``every`` frames (option, default 50):
    ``theta`` is piecewise constant over time and the ball is simulated with it.
``"extrapolation"``
    option ``param`` (default ``"g"``) and ``fraction`` (default 0.5): train draws that parameter
    uniformly from the lowest ``fraction`` of its range, test uniformly from above it. The other
    parameters are interleaved as usual. ``extras["distance"]`` (N,) holds the signed distance of
    the value from the training range's upper end, in fractions of the prior range (<= 0 in
    training, in ``[0, 1 - fraction]`` in test), to bin a sensitivity plot by.
``"noisy"``
    as interleaved; in the train split ``labels = theta + N(0, (label_noise * range)^2)`` per video
    (option ``label_noise``, default 0.05 of each parameter's range), ``theta`` stays true. Test
    labels are the truth.
``"simplified"``
    train: ``d`` and ``r`` fixed (option ``fixed``, default the centre of sub-range 4 of each,
    i.e. 45% up their range, a training sub-range), ``e`` and ``g`` interleaved; test: the full
    model, all four interleaved.

Initial states come from ``physics.sample_state0``. Nuisances (``nuisance`` dict) are passed to
``render.render``, except ``floor_offset``: each video then draws its floor height
``U(0, floor_offset)`` m, is simulated on that floor and filmed by the fixed camera framed on
floor 0, so the ball appears lifted, as when the paper randomised the height of the plane.
``Dataset.floor`` holds the true floor.

Determinism
-----------
Video ``i`` of a split draws everything (parameters, initial state, floor, label noise, pixel
nuisances) from its own stream ``SeedSequence(seed, spawn_key=(split_id, i))``, so the bytes do
not depend on the chunk size, a dataset of n videos is a prefix of one of more videos, and
``make_dataset`` equals ``load(generate(...))`` for the same arguments.

On disk
-------
A directory with ``frames.npy``, ``states.npy``, ``theta.npy``, ``labels.npy``, ``floor.npy``,
``extra_<name>.npy`` and ``meta.json``. ``generate`` writes into ``.<name>.partial`` beside it:
arrays are preallocated with ``np.lib.format.open_memmap`` and filled chunk by chunk (each chunk
mapped on its own, so memory stays bounded); ``progress.json`` records the videos done after every
chunk so a killed run resumes where it stopped; ``meta.json`` (with ``complete: true``, shapes,
dtypes and byte sizes) is written last and the directory is moved into place with ``os.replace``.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sysid_bench import __version__
from sysid_bench.core import physics
from sysid_bench.core._io import atomic_write, replace_folder
from sysid_bench.core._validate import check_positive_int
from sysid_bench.core.estimator import Observation
from sysid_bench.core.render import check_size, render

__all__ = [
    "SUBRANGES_TRAIN",
    "SUBRANGES_TEST",
    "VARIANTS",
    "FORMAT_VERSION",
    "subrange_bounds",
    "Dataset",
    "make_dataset",
    "generate",
    "load",
]

SUBRANGES_TRAIN = (0, 2, 4, 6, 8)
SUBRANGES_TEST = (1, 3, 5, 7, 9)
VARIANTS = ("interleaved", "changing", "extrapolation", "noisy", "simplified")
#: Bump when the files or their meaning change; ``load`` refuses other versions.
FORMAT_VERSION = 1
_SPLITS = ("train", "test")
_ARRAYS = ("frames", "states", "theta", "labels", "floor")
_NUISANCES = ("blur", "occlusion", "drop", "noise", "floor_offset")
_VARIANT_OPTIONS = {
    "interleaved": {},
    "changing": {"every": 50},
    "extrapolation": {"param": "g", "fraction": 0.5},
    "noisy": {"label_noise": 0.05},
    "simplified": {"fixed": None},
}
_LO = np.array([physics.PRIOR[p][0] for p in physics.PARAMS])
_HI = np.array([physics.PRIOR[p][1] for p in physics.PARAMS])


def subrange_bounds(param: str, k: int) -> tuple[float, float]:
    """Bounds of sub-range ``k`` (0-9, from the low end) of parameter ``param``.

    Returns
    -------
    (lo, hi) : tuple of float
    """
    if param not in physics.PARAMS:
        raise ValueError(f"param: expected one of {physics.PARAMS}, got {param!r}")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k <= 9:
        raise ValueError(f"k: expected an integer sub-range in 0..9, got {k!r}")
    lo, hi = physics.PRIOR[param]
    w = (hi - lo) / 10.0
    return lo + k * w, lo + (k + 1) * w


@dataclass
class Dataset:
    """A split of videos with their true states and parameters.

    Attributes
    ----------
    frames : ndarray, shape (N, T, H, W), uint8
    states : ndarray, shape (N, T, 4), float64
        True ``[x, y, vx, vy]``.
    theta : ndarray, shape (N, T, 4), float64
        True parameters per frame (constant over T unless the variant is ``"changing"``).
    labels : ndarray, shape (N, T, 4), float64
        Training targets: ``theta`` except in the train split of ``"noisy"``.
    floor : ndarray, shape (N,), float64
        Floor height per video, metres.
    meta : dict
        ``seed``, ``split``, ``variant``, ``options``, ``prior``, ``subranges``, ``n``,
        ``n_frames``, ``size``, ``dt``, ``nuisance``, ``format_version``, ``version``.
    extras : dict of str to ndarray
        Per-video extras: ``distance`` (N,) for ``"extrapolation"``; ``dropped`` and
        ``occluded`` (N, T) bool when those nuisances are on.

    Arrays may be read-only memory maps (``load(mmap=True)``).
    """

    frames: np.ndarray
    states: np.ndarray
    theta: np.ndarray
    labels: np.ndarray
    floor: np.ndarray
    meta: dict[str, Any]
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def observation(self, i: int, positions: bool = False, state0: bool = False) -> Observation:
        """Video ``i`` as an ``Observation``.

        Parameters
        ----------
        i : int
        positions : bool
            Also give the true positions ``states[i, :, :2]`` (NaN on dropped frames).
        state0 : bool
            Also give the true initial state (the paper's privileged baselines).

        Returns
        -------
        Observation
            frames (T, H, W) uint8, ``dt`` of the dataset, ``floor`` of the video.
        """
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -n <= i < n:
            raise ValueError(f"i: expected a video index in [0, {n}), got {i!r}")
        pos = None
        if positions:
            pos = np.array(self.states[i, :, :2], dtype=np.float64)
            if "dropped" in self.extras:
                pos[np.asarray(self.extras["dropped"][i])] = np.nan
        return Observation(
            frames=np.asarray(self.frames[i]),
            positions=pos,
            dt=float(self.meta.get("dt", physics.DT)),
            floor=float(self.floor[i]),
            state0=np.array(self.states[i, 0], dtype=np.float64) if state0 else None,
        )


# ---------------------------------------------------------------------------------------------
# configuration
def _config(split, n, seed, variant, n_frames, size, nuisance, variant_options) -> dict:
    """Validate arguments into the JSON-able config that fully determines a dataset."""
    if split not in _SPLITS:
        raise ValueError(f"split: expected 'train' or 'test', got {split!r}")
    n = check_positive_int(n, "n")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
    n_frames = check_positive_int(n_frames, "n_frames", minimum=2)
    h, w = check_size(size)
    if not isinstance(nuisance, (dict, type(None))):
        raise ValueError(f"nuisance: expected a dict or None, got {type(nuisance).__name__}")
    nuis = {} if nuisance is None else dict(nuisance)
    bad = sorted(set(nuis) - set(_NUISANCES))
    if bad:
        raise ValueError(f"nuisance: expected keys among {_NUISANCES}, got unknown {bad}")
    nuis = {k: float(v) for k, v in sorted(nuis.items())}
    # let render validate the ranges now, on a 1-frame dummy, so a bad value fails before work
    render(
        np.array([[[5.0, 5.0, 0.0, 0.0]]]),
        (h, w),
        seed=0,
        **{k: v for k, v in nuis.items() if k != "floor_offset"},
    )
    fo = nuis.get("floor_offset", 0.0)
    if not 0.0 <= fo <= physics.BOX_WIDTH:
        raise ValueError(f"nuisance: expected floor_offset in [0, 10] m, got {fo!r}")

    allowed = _VARIANT_OPTIONS[variant]
    bad = sorted(set(variant_options) - set(allowed))
    if bad:
        raise ValueError(
            f"variant_options: variant {variant!r} takes {sorted(allowed) or 'no options'}, got {bad}"
        )
    opts = {**allowed, **variant_options}
    if variant == "changing":
        opts["every"] = check_positive_int(opts["every"], "every")
    elif variant == "extrapolation":
        if opts["param"] not in physics.PARAMS:
            raise ValueError(f"param: expected one of {physics.PARAMS}, got {opts['param']!r}")
        f = opts["fraction"]
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 1:
            raise ValueError(f"fraction: expected a number in (0, 1), got {f!r}")
        opts["fraction"] = float(f)
    elif variant == "noisy":
        s = opts["label_noise"]
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 <= s <= 1:
            raise ValueError(f"label_noise: expected a fraction of the range in [0, 1], got {s!r}")
        opts["label_noise"] = float(s)
    elif variant == "simplified":
        fixed = opts["fixed"]
        if fixed is None:
            fixed = {
                p: _LO[i] + 0.45 * (_HI[i] - _LO[i])
                for i, p in enumerate(physics.PARAMS)
                if p in "dr"
            }
        if not isinstance(fixed, dict) or not set(fixed) <= set(physics.PARAMS) or not fixed:
            raise ValueError(
                f"fixed: expected a dict of parameter values, e.g. {{'d': 0.02}}, got {fixed!r}"
            )
        for p, v in fixed.items():
            lo, hi = physics.PRIOR[p]
            if not lo <= float(v) <= hi:
                raise ValueError(f"fixed: expected {p} in [{lo}, {hi}], got {v!r}")
        opts["fixed"] = {p: float(fixed[p]) for p in physics.PARAMS if p in fixed}

    subr = SUBRANGES_TRAIN if split == "train" else SUBRANGES_TEST
    return {
        "format_version": FORMAT_VERSION,
        "version": __version__,
        "seed": int(seed),
        "split": split,
        "variant": variant,
        "options": opts,
        "n": n,
        "n_frames": n_frames,
        "size": [h, w],
        "dt": physics.DT,
        "nuisance": nuis,
        "prior": {p: list(physics.PRIOR[p]) for p in physics.PARAMS},
        "subranges": list(subr),
    }


# ---------------------------------------------------------------------------------------------
# generation of one chunk
def _video_draws(cfg: dict, i: int):
    """Everything random about video ``i`` except the rendering, from its own stream."""
    rng = np.random.default_rng(
        np.random.SeedSequence(cfg["seed"], spawn_key=(_SPLITS.index(cfg["split"]), i))
    )
    t = cfg["n_frames"]
    variant, opts, train = cfg["variant"], cfg["options"], cfg["split"] == "train"
    subr = cfg["subranges"]
    distance = 0.0
    if variant == "changing":
        n_seg = -(-t // opts["every"])
        seg = physics.sample_theta(n_seg, rng, subr)
        theta = np.repeat(seg, opts["every"], axis=0)[:t]
    else:
        theta = physics.sample_theta(1, rng, subr)[0]
        if variant == "extrapolation":
            j = physics.PARAMS.index(opts["param"])
            f = opts["fraction"]
            u = rng.random()
            frac = f * u if train else f + (1.0 - f) * u
            theta[j] = _LO[j] + frac * (_HI[j] - _LO[j])
            distance = frac - f
        elif variant == "simplified" and train:
            for p, v in opts["fixed"].items():
                theta[physics.PARAMS.index(p)] = v
        theta = np.broadcast_to(theta, (t, 4))
    fo = cfg["nuisance"].get("floor_offset", 0.0)
    floor = rng.uniform(0.0, fo) if fo > 0 else 0.0
    state0 = physics.sample_state0(1, rng, floor=floor)[0]
    labels = theta
    if variant == "noisy" and train and opts["label_noise"] > 0:
        labels = theta + rng.normal(0.0, opts["label_noise"] * (_HI - _LO))
    return theta, labels, state0, floor, distance, rng


def _chunk(cfg: dict, i0: int, i1: int) -> dict[str, np.ndarray]:
    """Arrays of videos ``i0:i1``."""
    draws = [_video_draws(cfg, i) for i in range(i0, i1)]
    theta = np.stack([d[0] for d in draws])
    labels = np.stack([d[1] for d in draws])
    state0 = np.stack([d[2] for d in draws])
    floor = np.array([d[3] for d in draws], dtype=np.float64)
    rngs = [d[5] for d in draws]
    # constant parameters are simulated as (B, 4): the simulator's fast path
    th_sim = theta if cfg["variant"] == "changing" else theta[:, 0]
    states = physics.simulate(th_sim, state0, n_frames=cfg["n_frames"], dt=cfg["dt"], floor=floor)
    nuis = {k: v for k, v in cfg["nuisance"].items() if k != "floor_offset"}
    # the camera is fixed, framed on floor 0: a raised floor shows as a lifted ball
    frames, info = render(
        states, tuple(cfg["size"]), floor=0.0, seed=rngs, dt=cfg["dt"], return_info=True, **nuis
    )
    out = {
        "frames": frames,
        "states": states,
        "theta": np.ascontiguousarray(theta, dtype=np.float64),
        "labels": np.ascontiguousarray(labels, dtype=np.float64),
        "floor": floor,
    }
    for name, arr in _extra_arrays(cfg, draws, info).items():
        out["extra_" + name] = arr
    return out


def _extra_arrays(cfg: dict, draws, info) -> dict[str, np.ndarray]:
    extras = {}
    if cfg["variant"] == "extrapolation":
        extras["distance"] = np.array([d[4] for d in draws], dtype=np.float64)
    if cfg["nuisance"].get("drop", 0.0) > 0:
        extras["dropped"] = info["dropped"]
    if cfg["nuisance"].get("occlusion", 0.0) > 0:
        extras["occluded"] = info["occluded"]
    return extras


def _layout(cfg: dict) -> dict[str, tuple[tuple[int, ...], str]]:
    """Shape and dtype of every array file of a dataset."""
    n, t = cfg["n"], cfg["n_frames"]
    h, w = cfg["size"]
    lay = {
        "frames": ((n, t, h, w), "uint8"),
        "states": ((n, t, 4), "float64"),
        "theta": ((n, t, 4), "float64"),
        "labels": ((n, t, 4), "float64"),
        "floor": ((n,), "float64"),
    }
    if cfg["variant"] == "extrapolation":
        lay["extra_distance"] = ((n,), "float64")
    if cfg["nuisance"].get("drop", 0.0) > 0:
        lay["extra_dropped"] = ((n, t), "bool")
    if cfg["nuisance"].get("occlusion", 0.0) > 0:
        lay["extra_occluded"] = ((n, t), "bool")
    return lay


def _as_dataset(arrays: dict[str, np.ndarray], meta: dict) -> Dataset:
    extras = {k[len("extra_") :]: v for k, v in arrays.items() if k.startswith("extra_")}
    return Dataset(**{k: arrays[k] for k in _ARRAYS}, meta=meta, extras=extras)


def make_dataset(
    split: str = "train",
    n: int = 100,
    seed: int = 0,
    variant: str = "interleaved",
    n_frames: int = physics.N_FRAMES,
    size=(28, 28),
    nuisance: dict | None = None,
    *,
    chunk: int = 500,
    **variant_options,
) -> Dataset:
    """Generate a split in memory.

    Parameters
    ----------
    split : {"train", "test"}
    n : int
        Number of videos N.
    seed : int
        Non-negative; same seed, same arrays.
    variant : str
        One of ``VARIANTS`` (see the module docstring).
    n_frames : int
        Frames per video T.
    size : (int, int)
        ``(H, W)`` of the frames.
    nuisance : dict, optional
        ``blur``, ``occlusion``, ``drop``, ``noise`` (see ``render.render``) and
        ``floor_offset`` (random floor height per video, metres).
    chunk : int
        Videos simulated and rendered at once (bounds scratch memory; no effect on the result).
    **variant_options
        Options of the variant: ``every`` (changing), ``param``, ``fraction`` (extrapolation),
        ``label_noise`` (noisy), ``fixed`` (simplified).

    Returns
    -------
    Dataset
    """
    cfg = _config(split, n, seed, variant, n_frames, size, nuisance, variant_options)
    chunk = check_positive_int(chunk, "chunk")
    lay = _layout(cfg)
    arrays = {k: np.empty(shape, dtype=dt) for k, (shape, dt) in lay.items()}
    for i0 in range(0, cfg["n"], chunk):
        i1 = min(cfg["n"], i0 + chunk)
        for k, v in _chunk(cfg, i0, i1).items():
            arrays[k][i0:i1] = v
    return _as_dataset(arrays, {**cfg, "complete": True})


# ---------------------------------------------------------------------------------------------
# disk
def _write_json(path: Path, obj: dict) -> None:
    atomic_write(path, json.dumps(obj, indent=1, sort_keys=True))


def _read_json(path: Path) -> dict | None:
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError):
        return None


def _prepare_partial(tmp: Path, cfg: dict, lay) -> int:
    """Ready ``tmp`` for writing; return how many videos are already done there."""
    prog = _read_json(tmp / "progress.json")
    if prog is not None and prog.get("config") == cfg:
        ok = all((tmp / f"{k}.npy").is_file() for k in lay)
        if ok:
            return int(prog["done"])
    # stale or foreign partial run: start again from nothing
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for k, (shape, dt) in lay.items():
        mm = np.lib.format.open_memmap(tmp / f"{k}.npy", mode="w+", dtype=np.dtype(dt), shape=shape)
        mm.flush()
        del mm
    _write_json(tmp / "progress.json", {"config": cfg, "done": 0})
    return 0


def _write_rows(file: Path, rows: np.ndarray, i0: int) -> None:
    """Write ``rows`` at row ``i0`` of the .npy ``file`` through a memmap of just that region.

    Mapping only the chunk (and dropping the map after) keeps the written pages out of this
    process's resident memory.
    """
    mm = np.load(file, mmap_mode="r+")
    offset, shape, dtype = mm.offset, mm.shape, mm.dtype
    del mm
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
    part = np.memmap(
        file, dtype=dtype, mode="r+", offset=offset + i0 * row_bytes, shape=(len(rows), *shape[1:])
    )
    part[:] = rows
    part.flush()
    del part


def generate(
    path,
    split: str = "train",
    n: int = 10_000,
    seed: int = 0,
    variant: str = "interleaved",
    chunk: int = 500,
    progress: bool = True,
    *,
    n_frames: int = physics.N_FRAMES,
    size=(28, 28),
    nuisance: dict | None = None,
    overwrite: bool = False,
    **variant_options,
) -> Path:
    """Generate a split to the directory ``path``, chunk by chunk, resumable and atomic.

    Parameters
    ----------
    path : str or Path
        Directory to create. If it already holds a complete dataset with the same
        configuration, nothing is done.
    split, n, seed, variant, n_frames, size, nuisance, **variant_options
        As in :func:`make_dataset` (same arguments give the same arrays).
    chunk : int
        Videos per chunk; bounds memory, does not change the bytes written.
    progress : bool
        Show a tqdm progress bar.
    overwrite : bool
        Replace an existing dataset with a different configuration.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    FileExistsError
        ``path`` exists with another configuration (or is not a dataset) and ``overwrite`` is
        False.
    """
    from tqdm.auto import tqdm

    cfg = _config(split, n, seed, variant, n_frames, size, nuisance, variant_options)
    chunk = check_positive_int(chunk, "chunk")
    path = Path(path)
    if path.is_dir() and not any(path.iterdir()):
        path.rmdir()  # an empty directory made beforehand: take its place
    if path.exists():
        meta = _read_json(path / "meta.json")
        if meta is not None and meta.get("config") == cfg and meta.get("complete"):
            return path
        if not overwrite:
            raise FileExistsError(
                f"path: {path} exists and holds another configuration or no complete dataset; "
                "pass overwrite=True to replace it"
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    lay = _layout(cfg)
    done = _prepare_partial(tmp, cfg, lay)
    with tqdm(
        total=cfg["n"], initial=done, unit="video", desc=f"{split}/{variant}", disable=not progress
    ) as bar:
        for i0 in range(done, cfg["n"], chunk):
            i1 = min(cfg["n"], i0 + chunk)
            for k, v in _chunk(cfg, i0, i1).items():
                _write_rows(tmp / f"{k}.npy", v, i0)
            # record progress only once the rows are on disk, so a resume never skips videos
            _write_json(tmp / "progress.json", {"config": cfg, "done": i1})
            bar.update(i1 - i0)

    arrays = {
        k: {"shape": list(shape), "dtype": dt, "bytes": (tmp / f"{k}.npy").stat().st_size}
        for k, (shape, dt) in lay.items()
    }
    (tmp / "progress.json").unlink()
    _write_json(tmp / "meta.json", {**cfg, "config": cfg, "complete": True, "arrays": arrays})
    return replace_folder(tmp, path)  # overwrite: the old one moved aside, then dropped


def load(path, mmap: bool = True) -> Dataset:
    """Load a dataset written by :func:`generate`.

    Parameters
    ----------
    path : str or Path
    mmap : bool
        Memory-map the arrays read-only instead of reading them into memory.

    Returns
    -------
    Dataset

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValueError
        Not a complete dataset, another ``format_version``, or a missing, truncated or
        mis-shaped array file; the message says which.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"path: no dataset at {path}")
    if not path.is_dir():
        raise ValueError(f"path: expected a dataset directory, got a file {path}")
    meta_file = path / "meta.json"
    if not meta_file.is_file():
        raise ValueError(
            f"path: {path} has no meta.json; it is not a complete dataset "
            "(an interrupted generation leaves files without it)"
        )
    meta = _read_json(meta_file)
    if meta is None:
        raise ValueError(f"path: {meta_file} is not valid JSON")
    ver = meta.get("format_version")
    if ver != FORMAT_VERSION:
        raise ValueError(
            f"path: {path} has format_version {ver!r}, this sysid_bench reads {FORMAT_VERSION}; "
            "regenerate it with generate()"
        )
    if not meta.get("complete"):
        raise ValueError(f"path: {path} is marked incomplete in meta.json")
    arrays = {}
    for k, spec in meta.get("arrays", {}).items():
        f = path / f"{k}.npy"
        if not f.is_file():
            raise ValueError(f"path: {path} is missing {f.name}")
        size = f.stat().st_size
        if size != spec["bytes"]:
            raise ValueError(
                f"path: {f.name} is {size} bytes, meta.json says {spec['bytes']} (truncated or altered)"
            )
        try:
            a = np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"path: cannot read {f.name}: {exc}") from exc
        if list(a.shape) != spec["shape"] or str(a.dtype) != spec["dtype"]:
            raise ValueError(
                f"path: {f.name} has shape {a.shape} dtype {a.dtype}, meta.json says "
                f"{tuple(spec['shape'])} {spec['dtype']}"
            )
        arrays[k] = a
    missing = [k for k in _ARRAYS if k not in arrays]
    if missing:
        raise ValueError(f"path: meta.json of {path} lists no {missing}")
    meta = {k: v for k, v in meta.items() if k != "config"}
    return _as_dataset(arrays, meta)
