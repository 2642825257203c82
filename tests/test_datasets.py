import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sysid_bench.core import datasets as D
from sysid_bench.core import physics
from sysid_bench.core.estimator import Observation
from sysid_bench.core.tracking import track_batch

SMALL = dict(n_frames=20, size=(28, 28))


def _files(path):
    return {p.name: p.read_bytes() for p in sorted(path.iterdir())}


def _subrange_index(theta):
    """Sub-range 0-9 of every value, (..., 4) ints; values within 1e-9 of a border are -1."""
    u = physics.normalise_theta(theta) * 10
    k = np.floor(u).astype(int)
    on_border = np.abs(u - np.round(u)) < 1e-9
    return np.where(on_border, -1, k)


def test_subrange_bounds():
    assert D.subrange_bounds("e", 0) == pytest.approx((0.6, 0.64))
    assert D.subrange_bounds("g", 9) == pytest.approx((-7.41, -6.81))
    lo, hi = D.subrange_bounds("d", 3)
    assert hi - lo == pytest.approx((0.05 - 0.0005) / 10)
    with pytest.raises(ValueError, match="param"):
        D.subrange_bounds("m", 0)
    with pytest.raises(ValueError, match="k"):
        D.subrange_bounds("e", 10)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    variant=st.sampled_from(["interleaved", "changing", "noisy", "simplified"]),
)
def test_splits_never_share_a_subrange(seed, variant):
    opts = {"every": 2} if variant == "changing" else {}
    kw = dict(n=6, seed=seed, variant=variant, n_frames=6, size=(8, 8), **opts)
    tr = D.make_dataset("train", **kw)
    te = D.make_dataset("test", **kw)
    k_tr, k_te = _subrange_index(tr.theta), _subrange_index(te.theta)
    for j, p in enumerate(physics.PARAMS):
        if variant == "simplified" and p in "dr":
            # fixed in training at 45% of the range: inside sub-range 4, a training one
            assert set(k_tr[..., j].ravel()) == {4}
        else:
            assert set(k_tr[..., j].ravel()) <= set(D.SUBRANGES_TRAIN) | {-1}
        assert set(k_te[..., j].ravel()) <= set(D.SUBRANGES_TEST) | {-1}
        assert not set(k_tr[..., j].ravel()) & set(k_te[..., j].ravel()) - {-1}


def test_dataset_shapes_and_physics_consistency():
    ds = D.make_dataset("train", n=7, seed=1, **SMALL)
    assert len(ds) == 7
    assert ds.frames.shape == (7, 20, 28, 28) and ds.frames.dtype == np.uint8
    assert ds.states.shape == ds.theta.shape == ds.labels.shape == (7, 20, 4)
    assert ds.floor.shape == (7,)
    np.testing.assert_array_equal(ds.labels, ds.theta)
    assert (ds.theta == ds.theta[:, :1]).all()  # constant over time
    re = physics.simulate(ds.theta[:, 0], ds.states[:, 0], n_frames=20, floor=ds.floor)
    np.testing.assert_array_equal(re, ds.states)
    pos = track_batch(ds.frames)
    assert np.abs(pos - ds.states[..., :2]).max() < 0.1
    for key in ("seed", "split", "variant", "n", "n_frames", "size", "format_version", "version"):
        assert key in ds.meta
    assert ds.meta["subranges"] == list(D.SUBRANGES_TRAIN)


def test_same_seed_same_arrays_other_seed_or_split_differs():
    a = D.make_dataset("train", n=4, seed=5, **SMALL)
    b = D.make_dataset("train", n=4, seed=5, **SMALL)
    c = D.make_dataset("train", n=4, seed=6, **SMALL)
    t = D.make_dataset("test", n=4, seed=5, **SMALL)
    for k in ("frames", "states", "theta"):
        assert getattr(a, k).tobytes() == getattr(b, k).tobytes()
        assert getattr(a, k).tobytes() != getattr(c, k).tobytes()
        assert getattr(a, k).tobytes() != getattr(t, k).tobytes()


def test_chunking_and_prefix_do_not_change_videos():
    nuis = dict(noise=5.0, drop=0.2, occlusion=0.2, blur=0.5, floor_offset=1.0)
    a = D.make_dataset("train", n=9, seed=2, chunk=2, nuisance=nuis, **SMALL)
    b = D.make_dataset("train", n=9, seed=2, chunk=9, nuisance=nuis, **SMALL)
    c = D.make_dataset("train", n=4, seed=2, chunk=3, nuisance=nuis, **SMALL)
    for k in ("frames", "states", "theta", "labels", "floor"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        np.testing.assert_array_equal(getattr(a, k)[:4], getattr(c, k))
    np.testing.assert_array_equal(a.extras["dropped"], b.extras["dropped"])


def test_generate_same_bytes_independent_of_chunk_and_equal_to_memory(tmp_path):
    kw = dict(n=11, seed=3, progress=False, nuisance=dict(noise=3.0, drop=0.1), **SMALL)
    p1 = D.generate(tmp_path / "a", "test", chunk=4, **kw)
    p2 = D.generate(tmp_path / "b", "test", chunk=11, **kw)
    p3 = D.generate(tmp_path / "c", "test", chunk=1, **kw)
    f1 = _files(p1)
    assert set(f1) >= {
        "frames.npy",
        "states.npy",
        "theta.npy",
        "labels.npy",
        "floor.npy",
        "meta.json",
    }
    assert f1 == _files(p2) == _files(p3)
    assert not list(tmp_path.glob(".*partial"))
    ds = D.load(p1)
    assert isinstance(ds.frames, np.memmap) and not ds.frames.flags.writeable
    mem = D.make_dataset("test", n=11, seed=3, nuisance=dict(noise=3.0, drop=0.1), **SMALL)
    for k in ("frames", "states", "theta", "labels", "floor"):
        np.testing.assert_array_equal(getattr(ds, k), getattr(mem, k))
    np.testing.assert_array_equal(ds.extras["dropped"], mem.extras["dropped"])
    full = D.load(p1, mmap=False)
    assert not isinstance(full.frames, np.memmap)
    assert full.meta["complete"] and full.meta["format_version"] == D.FORMAT_VERSION


def test_generate_existing_path(tmp_path):
    kw = dict(n=3, seed=0, progress=False, **SMALL)
    p = D.generate(tmp_path / "d", **kw)
    before = (p / "frames.npy").stat().st_mtime_ns
    assert D.generate(tmp_path / "d", **kw) == p  # same configuration: nothing to do
    assert (p / "frames.npy").stat().st_mtime_ns == before
    (tmp_path / "empty").mkdir()
    assert D.load(D.generate(tmp_path / "empty", **kw)).meta["n"] == 3  # an empty dir is fine
    with pytest.raises(FileExistsError, match="overwrite"):
        D.generate(tmp_path / "d", **{**kw, "seed": 1})
    D.generate(tmp_path / "d", overwrite=True, **{**kw, "seed": 1})
    assert D.load(p).meta["seed"] == 1


def test_killed_generation_leaves_nothing_loadable_and_resumes(tmp_path, monkeypatch):
    kw = dict(n=10, seed=4, chunk=3, progress=False, **SMALL)
    real = D._chunk
    calls = []

    def dying(cfg, i0, i1):
        calls.append(i0)
        if len(calls) == 3:
            raise KeyboardInterrupt("killed")
        return real(cfg, i0, i1)

    monkeypatch.setattr(D, "_chunk", dying)
    with pytest.raises(KeyboardInterrupt):
        D.generate(tmp_path / "r", **kw)
    with pytest.raises(FileNotFoundError, match="no dataset"):
        D.load(tmp_path / "r")
    partial = tmp_path / ".r.partial"
    assert partial.is_dir() and json.loads((partial / "progress.json").read_text())["done"] == 6
    with pytest.raises(ValueError, match="meta.json"):
        D.load(partial)
    calls.clear()
    monkeypatch.setattr(D, "_chunk", lambda cfg, i0, i1: (calls.append(i0), real(cfg, i0, i1))[1])
    D.generate(tmp_path / "r", **kw)
    assert calls == [6, 9]  # resumed after the two finished chunks
    clean = D.generate(tmp_path / "clean", **kw)
    assert _files(tmp_path / "r") == _files(clean)


def test_partial_of_other_configuration_is_restarted(tmp_path, monkeypatch):
    kw = dict(n=6, chunk=2, progress=False, **SMALL)
    real = D._chunk

    def dying(cfg, i0, i1):
        if i0 >= 2:
            raise KeyboardInterrupt
        return real(cfg, i0, i1)

    monkeypatch.setattr(D, "_chunk", dying)
    with pytest.raises(KeyboardInterrupt):
        D.generate(tmp_path / "x", seed=1, **kw)
    monkeypatch.setattr(D, "_chunk", real)
    D.generate(tmp_path / "x", seed=2, **kw)
    ref = D.generate(tmp_path / "ref", seed=2, **kw)
    assert _files(tmp_path / "x") == _files(ref)


@pytest.fixture
def saved(tmp_path):
    return D.generate(tmp_path / "s", n=3, seed=0, progress=False, **SMALL)


def test_load_version_mismatch(saved):
    meta = json.loads((saved / "meta.json").read_text())
    meta["format_version"] = D.FORMAT_VERSION + 1
    (saved / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format_version"):
        D.load(saved)


def test_load_truncated_array(saved):
    f = saved / "frames.npy"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="frames.npy.*truncated"):
        D.load(saved)


def test_load_missing_pieces(saved, tmp_path):
    with pytest.raises(FileNotFoundError):
        D.load(tmp_path / "nothing")
    (saved / "theta.npy").unlink()
    with pytest.raises(ValueError, match="missing theta.npy"):
        D.load(saved)
    (saved / "meta.json").unlink()
    with pytest.raises(ValueError, match="meta.json"):
        D.load(saved)


def test_changing_parameters():
    ds = D.make_dataset("test", n=5, seed=0, variant="changing", n_frames=120, size=(28, 28))
    th = ds.theta
    changes = np.flatnonzero((np.diff(th, axis=1) != 0).any(axis=(0, 2))) + 1
    np.testing.assert_array_equal(changes, [50, 100])
    for s in (slice(0, 50), slice(50, 100), slice(100, 120)):
        assert (th[:, s] == th[:, s.start : s.start + 1]).all()
    re = physics.simulate(th, ds.states[:, 0], n_frames=120, floor=ds.floor)
    np.testing.assert_array_equal(re, ds.states)
    ds10 = D.make_dataset("test", n=2, seed=0, variant="changing", every=10, **SMALL)
    assert (np.diff(ds10.theta, axis=1) != 0).any(axis=(0, 2)).sum() == 1


def test_extrapolation():
    kw = dict(
        n=40, seed=1, variant="extrapolation", param="e", fraction=0.4, n_frames=5, size=(8, 8)
    )
    tr, te = D.make_dataset("train", **kw), D.make_dataset("test", **kw)
    border = 0.6 + 0.4 * 0.4
    assert (tr.theta[..., 0] <= border).all() and (te.theta[..., 0] >= border).all()
    np.testing.assert_allclose(te.extras["distance"], (te.theta[:, 0, 0] - border) / 0.4)
    assert (tr.extras["distance"] <= 0).all()
    assert 0 <= te.extras["distance"].min() and te.extras["distance"].max() <= 0.6
    assert te.extras["distance"].max() > 0.4  # reaches far out
    assert tr.meta["options"] == {"param": "e", "fraction": 0.4}


def test_noisy_labels():
    kw = dict(n=300, seed=1, variant="noisy", label_noise=0.1, n_frames=3, size=(8, 8))
    tr, te = D.make_dataset("train", **kw), D.make_dataset("test", **kw)
    err = (tr.labels - tr.theta)[:, 0] / (
        physics.denormalise_theta(np.ones(4)) - physics.denormalise_theta(np.zeros(4))
    )
    np.testing.assert_allclose(err.std(axis=0), 0.1, rtol=0.15)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=0.025)
    assert (tr.labels == tr.labels[:, :1]).all()  # one label per video
    np.testing.assert_array_equal(te.labels, te.theta)
    # theta stays the truth: the same draws as the clean interleaved split
    clean = D.make_dataset("train", n=300, seed=1, n_frames=3, size=(8, 8))
    np.testing.assert_array_equal(tr.theta, clean.theta)


def test_simplified():
    kw = dict(n=10, seed=0, variant="simplified", n_frames=3, size=(8, 8))
    tr, te = D.make_dataset("train", **kw), D.make_dataset("test", **kw)
    assert np.unique(tr.theta[..., 2]).size == 1 and np.unique(tr.theta[..., 3]).size == 1
    np.testing.assert_allclose(tr.theta[0, 0, 2:], [0.0005 + 0.45 * 0.0495, 0.45 * 0.7])
    assert np.unique(te.theta[:, 0, 2]).size == 10 and np.unique(te.theta[:, 0, 3]).size == 10
    tr2 = D.make_dataset("train", fixed={"d": 0.001}, **kw)
    assert (tr2.theta[..., 2] == 0.001).all() and np.unique(tr2.theta[:, 0, 3]).size == 10


def test_floor_offset_nuisance():
    ds = D.make_dataset("train", n=8, seed=0, nuisance={"floor_offset": 1.0}, **SMALL)
    assert (ds.floor >= 0).all() and (ds.floor <= 1).all() and ds.floor.std() > 0
    assert (ds.states[..., 1] >= ds.floor[:, None] - 1e-9).all()
    # the fixed camera is framed on floor 0: tracking gives world heights, floor included
    pos = track_batch(ds.frames, 0.0)
    ok = np.isfinite(pos).all(axis=-1)
    assert ok.mean() > 0.9
    assert np.abs(pos[ok] - ds.states[..., :2][ok]).max() < 0.1


def test_observation():
    ds = D.make_dataset("train", n=3, seed=0, nuisance={"drop": 0.3}, **SMALL)
    o = ds.observation(1)
    assert isinstance(o, Observation)
    assert o.frames.shape == (20, 28, 28) and o.positions is None and o.state0 is None
    assert o.floor == ds.floor[1] and o.dt == physics.DT
    o = ds.observation(2, positions=True, state0=True)
    drop = ds.extras["dropped"][2]
    assert drop.any()
    assert np.isnan(o.positions[drop]).all()
    np.testing.assert_array_equal(o.positions[~drop], ds.states[2, ~drop, :2])
    np.testing.assert_array_equal(o.state0, ds.states[2, 0])
    with pytest.raises(ValueError, match="i:"):
        ds.observation(3)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(split="val"), "split"),
        (dict(n=0), "n"),
        (dict(seed=-1), "seed"),
        (dict(seed=1.5), "seed"),
        (dict(variant="weird"), "variant"),
        (dict(n_frames=1), "n_frames"),
        (dict(size=(28,)), "size"),
        (dict(size=(28, -1)), "size"),
        (dict(nuisance={"fog": 1.0}), "nuisance"),
        (dict(nuisance={"noise": -1.0}), "noise"),
        (dict(nuisance={"drop": 2.0}), "drop"),
        (dict(nuisance={"floor_offset": 20.0}), "floor_offset"),
        (dict(nuisance=[1]), "nuisance"),
        (dict(every=5), "variant_options"),
        (dict(variant="changing", every=0), "every"),
        (dict(variant="extrapolation", param="m"), "param"),
        (dict(variant="extrapolation", fraction=1.0), "fraction"),
        (dict(variant="noisy", label_noise=-0.1), "label_noise"),
        (dict(variant="simplified", fixed={"d": 1.0}), "fixed"),
        (dict(chunk=0), "chunk"),
    ],
)
def test_bad_input(kwargs, name):
    kw = dict(n=2, seed=0, n_frames=3)
    kw.update(kwargs)
    with pytest.raises(ValueError, match=name):
        D.make_dataset(**kw)
