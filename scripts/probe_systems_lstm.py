"""Can Vid2Param's recurrence read a system's parameters from its tracked points? A CPU probe.

Per system (``pendulum``, ``spring``, ``collision``) this trains only the recurrence of
``methods.vid2param.parts`` (``phi_z`` + LSTM cell fed the points' positions and difference
features, read as ``[h, c]``) and a ``GaussianHead`` on the normalised parameters with the
Gaussian NLL at every frame -- no frames, no encoder, no decoder, no KL. The positions are the
true observed points (``System.observe``) normalised by the view's ``extent`` exactly as the
network's targets (``data.normalise_points``), with Gaussian keypoint noise of ``--noise-px``
pixels of the system's default frame. Training batches are fresh draws from the train split
(``System.sample_cases(n, rng, "train")``, ``simulate``); every ``--eval-every`` steps the
normalised MSE per parameter and the 90% coverage after the last frame are measured on fixed
test-split trajectories (guessing the prior's middle scores 1/12 = 0.083).

Feature variants (what the LSTM cell gets beside ``phi_z(positions)``):

``a``  today's: velocity ``10 d1`` clamped to +-5, acceleration ``40 (vel_t - vel_{t-1})``
       (= ``400 d2``) clamped to +-10, as ``parts.Recurrence`` (checked against it at start).
``b``  the same two features with per-system scales making their median magnitude ~1 (measured
       on train-split draws with the noise, printed), same clamps.
``c``  ``b`` plus system evidence: pendulum -- the angle about the pivot as (sin, cos), the
       radius, the angular velocity and acceleration (scaled to ~1); collision -- the gap
       ``x2 - x1``, its rate, and each puck's velocity change at the velocity's scale (an
       impulse at a contact, unclamped up to +-10). The spring has no ``c``.
``d``  pendulum only: ``c`` plus the per-frame terms of the least-squares normal equations of
       ``alpha = k sin(angle) - b omega`` (alpha sin, sin^2, alpha omega, omega^2, omega sin),
       which the cell can sum so that the head reads ``k = g / L`` and ``b`` as their ratios.

Example (one thread, ~2-4 min a run)::

    OMP_NUM_THREADS=1 python scripts/probe_systems_lstm.py --systems pendulum --variants a b c \\
        --steps 300 --eval-every 100 --json runs/probe/pendulum.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from methods.vid2param.data import normalise_points  # noqa: E402
from methods.vid2param.model import gaussian_nll, position_names  # noqa: E402
from methods.vid2param.parts import GaussianHead, Recurrence  # noqa: E402
from sysid_bench.core import systems  # noqa: E402

SYSTEMS = ("pendulum", "spring", "collision")
VARIANTS = ("a", "b", "c", "d")
#: parts.Recurrence's scales and clamps (variant a).
VEL_SCALE, ACC_SCALE, VEL_CLAMP, ACC_CLAMP = 10.0, 40.0, 5.0, 10.0
#: Clamp of the variant-c evidence features (angle rates, impulses).
EVID_CLAMP = 10.0
DT = 0.05
Z90 = 1.6448536269514722


# ---------------------------------------------------------------------------------------------
# data
def draw(system, n: int, rng: np.random.Generator, split: str, n_frames: int,
         noise_px: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` trajectories of ``split``: normalised points (n, T, K, 2) with keypoint noise and
    normalised parameters (n, P), both float32."""
    theta, state0 = system.sample_cases(n, rng, split)
    states = system.simulate(theta, state0, n_frames=n_frames, dt=DT)
    pts = normalise_points(system.observe(states, theta), system.extent)
    if noise_px > 0:
        h, w = system.size
        sd = np.array([noise_px / w, noise_px / h])  # normalised x spans W pixels, y spans H
        pts = pts + rng.normal(size=pts.shape) * sd
    return pts.astype(np.float32), system.normalise(theta).astype(np.float32)


def differences(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second differences (N, T, D) of positions (N, T, D) as ``parts.Recurrence``
    forms them (0 before the frames they need): ``d1_t = p_t - p_{t-1}``, ``d2_t = d1_t -
    d1_{t-1}`` (``d1_0 = 0``, so ``d2_1`` would be ``d1_1``: set to 0 as the recurrence's
    ``n >= 2`` gate does)."""
    d1 = np.zeros_like(pos)
    d1[:, 1:] = pos[:, 1:] - pos[:, :-1]
    d2 = np.zeros_like(pos)
    d2[:, 2:] = d1[:, 2:] - d1[:, 1:-1]
    return d1, d2


def _angle(system, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pendulum's bob angle from straight down (unwrapped) and radius (normalised units)
    about the pivot (world (0, 0)) from normalised points (N, T, 1, 2)."""
    piv = normalise_points(np.zeros((1, 2)), system.extent)[0]
    x0, x1, y0, y1 = system.extent
    # back to an isotropic frame (the pendulum's view is square; kept general)
    dx = (pts[..., 0, 0] - piv[0]) * (x1 - x0)
    dy = (pts[..., 0, 1] - piv[1]) * (y1 - y0)
    ang = np.unwrap(np.arctan2(dx, -dy), axis=1)
    rad = np.hypot(dx, dy) / max(x1 - x0, y1 - y0)
    return ang, rad


def _median_abs(a: np.ndarray, skip: int, moving: np.ndarray) -> float:
    """Median |a| over frames >= ``skip`` of the components ``moving`` (D,) bool."""
    a = a[:, skip:]
    a = a.reshape(-1, a.shape[-1])
    return float(np.median(np.abs(a[:, moving]))) if moving.any() else 1.0


def _stats(a: np.ndarray, skip: int, moving: np.ndarray, clamp: float | None = None) -> dict:
    """Median, RMS and 99th percentile of |a| over the components ``moving``, and the share
    over ``clamp``."""
    a = a[:, skip:]
    a = np.abs(a.reshape(-1, a.shape[-1])[:, moving])
    out = {"median": float(np.median(a)), "rms": float(np.sqrt(np.mean(a**2))),
           "p99": float(np.percentile(a, 99))}
    if clamp is not None:
        out["clamped"] = float(np.mean(a > clamp))
    return out


def moving_components(clean: np.ndarray) -> np.ndarray:
    """(2K,) bool: the coordinates of clean points (N, T, K, 2) that move (the spring's and
    collision's y do not: keypoint noise there must not set the scales)."""
    pos = clean.reshape(*clean.shape[:2], -1)
    return np.ptp(pos, axis=1).max(0) > 1e-9


def measure_scales(system, pts: np.ndarray, moving: np.ndarray) -> dict:
    """Variant b's and c's feature scales from train-split points (N, T, K, 2) as fed (with
    the keypoint noise): each makes the median magnitude of its feature over the ``moving``
    coordinates 1."""
    pos = pts.reshape(*pts.shape[:2], -1)
    d1, d2 = differences(pos)
    sc = {"vel": 1.0 / _median_abs(d1, 1, moving), "acc": 1.0 / _median_abs(d2, 2, moving)}
    if system.name == "pendulum":
        ang, rad = _angle(system, pts)
        a1, a2 = differences(ang[..., None])
        one = np.ones(1, bool)
        sc.update({"rad": 1.0 / float(np.median(rad)), "omega": 1.0 / _median_abs(a1, 1, one),
                   "alpha": 1.0 / _median_abs(a2, 2, one)})
    if system.name == "collision":
        gap = pts[..., 1, 0] - pts[..., 0, 0]
        sc["gap"] = 1.0 / float(np.median(np.abs(gap)))
    return sc


def report_scales(name: str, clean: np.ndarray, pts: np.ndarray, moving: np.ndarray,
                  sc: dict) -> dict:
    """Print and return the magnitudes of the differences of clean points and of the variants'
    features of the same points with the keypoint noise, each (N, T, K, 2)."""
    d1c, d2c = differences(clean.reshape(*clean.shape[:2], -1))
    d1, d2 = differences(pts.reshape(*pts.shape[:2], -1))
    rows = {"clean d1": _stats(d1c, 1, moving), "clean d2": _stats(d2c, 2, moving),
            "noisy d1": _stats(d1, 1, moving), "noisy d2": _stats(d2, 2, moving),
            "a vel": _stats(VEL_SCALE * d1, 1, moving, VEL_CLAMP),
            "a acc": _stats(VEL_SCALE * ACC_SCALE * d2, 2, moving, ACC_CLAMP),
            "b vel": _stats(sc["vel"] * d1, 1, moving, VEL_CLAMP),
            "b acc": _stats(sc["acc"] * d2, 2, moving, ACC_CLAMP)}
    print(f"[{name}] scales: vel x{sc['vel']:.4g} acc x{sc['acc']:.4g} (today x10, x400)"
          + "".join(f" {k} x{v:.4g}" for k, v in sc.items() if k not in ("vel", "acc")))
    for k, v in rows.items():
        extra = f" over clamp {v['clamped']:.3f}" if "clamped" in v else ""
        print(f"[{name}]   |{k}|: median {v['median']:.3g} rms {v['rms']:.3g} "
              f"p99 {v['p99']:.3g}{extra}")
    return rows


def features(system, variant: str, pts: np.ndarray, sc: dict) -> tuple[np.ndarray, np.ndarray]:
    """The LSTM's inputs: ``z`` (N, T, 2K), the positions fed to ``phi_z``, and ``u`` (N, T, F),
    the features that bypass it, per ``variant`` (module docstring)."""
    pos = pts.reshape(*pts.shape[:2], -1)
    d1, d2 = differences(pos)
    if variant == "a":
        vel = VEL_SCALE * d1
        acc = ACC_SCALE * (vel - np.concatenate([np.zeros_like(vel[:, :1]), vel[:, :-1]], 1))
        acc[:, :2] = 0.0
        u = [np.clip(vel, -VEL_CLAMP, VEL_CLAMP), np.clip(acc, -ACC_CLAMP, ACC_CLAMP)]
    else:
        u = [np.clip(sc["vel"] * d1, -VEL_CLAMP, VEL_CLAMP),
             np.clip(sc["acc"] * d2, -ACC_CLAMP, ACC_CLAMP)]
    if variant in ("c", "d") and system.name == "pendulum":
        ang, rad = _angle(system, pts)
        a1, a2 = differences(ang[..., None])
        om = np.clip(sc["omega"] * a1, -EVID_CLAMP, EVID_CLAMP)
        al = np.clip(sc["alpha"] * a2, -EVID_CLAMP, EVID_CLAMP)
        sn = np.sin(ang)[..., None]
        u += [sn, np.cos(ang)[..., None], sc["rad"] * rad[..., None], om, al]
        if variant == "d":
            # the per-frame terms of the least-squares normal equations of
            # alpha = k sin(angle) - b omega: summed by the cell, their ratios give k = g / L, b
            ok = np.zeros_like(al)
            ok[:, 2:] = 1.0  # alpha is defined from the third frame
            u += [al * sn, ok * sn**2, al * om, ok * om**2, ok * om * sn]
    elif variant == "d":
        raise ValueError(f"variant: 'd' is defined for the pendulum, got {system.name}")
    elif variant == "c" and system.name == "collision":
        gap = pts[..., 1, 0] - pts[..., 0, 0]
        g1, _ = differences(gap[..., None])
        xs = pts[..., :, 0]  # (N, T, 2): the pucks' x
        v1, v2 = differences(xs)  # v2: the velocity change, an impulse at a contact
        u += [sc["gap"] * gap[..., None], np.clip(sc["vel"] * g1, -EVID_CLAMP, EVID_CLAMP),
              np.clip(sc["vel"] * v2, -EVID_CLAMP, EVID_CLAMP)]
    elif variant == "c":
        raise ValueError(f"variant: 'c' is defined for pendulum and collision, got {system.name}")
    return pos.astype(np.float32), np.concatenate(u, -1).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# model
def _recurrence_config(n_pos: int, hidden: int, feat: int) -> SimpleNamespace:
    """The fields ``parts.Recurrence`` reads, for a latent of the positions alone."""
    names = position_names(n_pos // 2)
    return SimpleNamespace(hidden=hidden, feat=feat, latent=n_pos, targets=names,
                           positions=names, roll_features=False, roll_stat="steps")


class Probe(nn.Module):
    """``parts.Recurrence``'s ``phi_z`` and LSTM fed ``[phi_z(z_t), u_t]``, read as ``[h, c]``
    by a ``parts.GaussianHead`` over the P normalised parameters.

    The LSTM is ``nn.LSTM`` (the same cell as ``Recurrence``'s ``nn.LSTMCell``, ~1.7x faster
    on one CPU thread) run in chunks of ``read_every`` frames, the head reading the state at
    each chunk's end.
    """

    def __init__(self, n_pos: int, n_u: int, n_par: int, hidden: int, feat: int):
        super().__init__()
        self.phi_z = nn.Sequential(nn.Linear(n_pos, feat), nn.ReLU())
        self.lstm = nn.LSTM(feat + n_u, hidden, batch_first=True)
        self.head = GaussianHead(2 * hidden, hidden, n_par)

    def states(self, z: torch.Tensor, u: torch.Tensor, read_every: int) -> torch.Tensor:
        """``[h, c]`` (B, n_reads, 2 hidden) after frames ``read_every``, ``2 read_every``, ...
        and the last of ``z`` (B, T, 2K), ``u`` (B, T, F)."""
        x = torch.cat([self.phi_z(z), u], -1)
        st, reads = None, []
        for i in range(0, x.shape[1], read_every):
            _, st = self.lstm(x[:, i:i + read_every], st)
            reads.append(torch.cat([st[0][0], st[1][0]], -1))
        return torch.stack(reads, 1)

    def forward(self, z: torch.Tensor, u: torch.Tensor, read_every: int):
        """Mean and std (B, n_reads, P) of the parameters at the reads of :meth:`states`."""
        return self.head(self.states(z, u, read_every))


def check_against_recurrence(sysobj, hidden: int, feat: int, seed: int) -> float:
    """Largest |difference| of ``[h, c]`` after 12 frames between a ``Probe`` fed variant a's
    features and ``parts.Recurrence`` stepping the same positions with the same weights."""
    rng = np.random.default_rng([seed, 5])
    pts, _ = draw(sysobj, 4, rng, "train", 12, 0.0)
    z, u = features(sysobj, "a", pts, {})
    n_pos = z.shape[-1]
    torch.manual_seed(seed)
    probe = Probe(n_pos, u.shape[-1], len(sysobj.params), hidden, feat)
    rec = Recurrence(_recurrence_config(n_pos, hidden, feat))
    rec.phi_z.load_state_dict(probe.phi_z.state_dict())
    lstm = probe.lstm
    rec.cell.load_state_dict({"weight_ih": lstm.weight_ih_l0, "weight_hh": lstm.weight_hh_l0,
                              "bias_ih": lstm.bias_ih_l0, "bias_hh": lstm.bias_hh_l0})
    zt, ut = torch.from_numpy(z), torch.from_numpy(u)
    with torch.no_grad():
        st = rec.init_state(zt.shape[0])
        for i in range(zt.shape[1]):
            st = rec(zt[:, i], st)
        hc = probe.states(zt, ut, 5)[:, -1]
    return float((hc - torch.cat([st.h, st.c], -1)).abs().max())


# ---------------------------------------------------------------------------------------------
# one run
def evaluate(probe: Probe, z: torch.Tensor, u: torch.Tensor, theta: torch.Tensor) -> dict:
    """nMSE and 90% coverage per parameter after the last frame, and their means."""
    with torch.no_grad():
        mu, sd = probe(z, u, z.shape[1])
    mu, sd = mu[:, 0], sd[:, 0]
    se = ((mu - theta) ** 2).mean(0)
    cov = ((mu - theta).abs() <= Z90 * sd).float().mean(0)
    return {"nmse": se.tolist(), "cov": cov.tolist(), "mean_nmse": float(se.mean())}


def run(name: str, variant: str, args, scales: dict) -> dict:
    """Train one probe on fresh train-split batches; evaluate on the fixed test trajectories."""
    s = systems.get(name)
    test_rng = np.random.default_rng([args.seed, 2, SYSTEMS.index(name)])
    pts_te, th_te = draw(s, args.n_test, test_rng, "test", args.frames, args.noise_px)
    z_te, u_te = (torch.from_numpy(a) for a in features(s, variant, pts_te, scales))
    th_te = torch.from_numpy(th_te)
    torch.manual_seed(args.seed)
    probe = Probe(z_te.shape[-1], u_te.shape[-1], len(s.params), args.hidden, args.feat)
    opt = torch.optim.Adam(probe.parameters(), lr=args.lr)
    rng = np.random.default_rng([args.seed, 1, SYSTEMS.index(name), VARIANTS.index(variant)])
    evals, t0 = [], time.perf_counter()
    for step in range(args.steps + 1):
        if step % args.eval_every == 0 or step == args.steps:
            ev = evaluate(probe, z_te, u_te, th_te)
            ev.update(step=step, seconds=round(time.perf_counter() - t0, 1))
            evals.append(ev)
            per = " ".join(f"{p} {m:.4f}/{c:.2f}" for p, m, c in zip(s.params, ev["nmse"],
                                                                   ev["cov"]))
            print(f"[{name} {variant}] step {step:4d} {ev['seconds']:6.1f}s mean nMSE "
                  f"{ev['mean_nmse']:.4f} | nMSE/cov90: {per}", flush=True)
        if step == args.steps:
            break
        pts, th = draw(s, args.batch, rng, "train", args.frames, args.noise_px)
        z, u = (torch.from_numpy(a) for a in features(s, variant, pts, scales))
        mu, sd = probe(z, u, args.read_every)
        loss = gaussian_nll(mu, sd, torch.from_numpy(th)[:, None, :]).mean()
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(probe.parameters(), args.clip)
        opt.step()
    return {"system": name, "variant": variant, "params": list(s.params), "evals": evals}


def _write_json(path: Path, obj) -> None:
    """Write ``obj`` as JSON atomically (``sysid_bench.core._io.atomic_write``)."""
    from sysid_bench.core._io import atomic_write

    atomic_write(path, json.dumps(obj, indent=1))


def _positive_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return v


def _nonneg_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--systems", nargs="+", choices=SYSTEMS, default=list(SYSTEMS))
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                    help="feature variants (c is skipped for the spring, d run for the "
                         "pendulum only)")
    ap.add_argument("--steps", type=_positive_int, default=300, help="Adam steps per run")
    ap.add_argument("--eval-every", type=_positive_int, default=100)
    ap.add_argument("--batch", type=_positive_int, default=64)
    ap.add_argument("--frames", type=_positive_int, default=200)
    ap.add_argument("--n-test", type=_positive_int, default=256, help="test-split trajectories")
    ap.add_argument("--hidden", type=_positive_int, default=128, help="LSTM size (V2PConfig)")
    ap.add_argument("--feat", type=_positive_int, default=128, help="phi_z size (V2PConfig)")
    ap.add_argument("--read-every", type=_positive_int, default=10,
                    help="the NLL is taken after every this many frames (and the last)")
    ap.add_argument("--lr", type=_nonneg_float, default=1e-3)
    ap.add_argument("--clip", type=_nonneg_float, default=10.0, help="gradient-norm clip")
    ap.add_argument("--noise-px", type=_nonneg_float, default=0.02,
                    help="keypoint noise, pixels of the system's default frame (clean trackers: "
                         "0.01-0.02 px RMS)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=_positive_int, default=1)
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    if args.frames < 3:
        ap.error(f"--frames: expected at least 3 (the second difference), got {args.frames}")
    torch.set_num_threads(args.threads)

    out = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
           "scales": {}, "runs": []}
    for name in args.systems:
        s = systems.get(name)
        err = check_against_recurrence(s, args.hidden, args.feat, args.seed)
        print(f"[{name}] variant a vs parts.Recurrence: max |d[h, c]| = {err:.2e}")
        if err > 1e-5:
            raise RuntimeError(f"variant a differs from parts.Recurrence by {err:.3g}")
        # the same 512 train-split draws, clean and with the keypoint noise
        clean, _ = draw(s, 512, np.random.default_rng([args.seed, 3]), "train", args.frames, 0.0)
        pts, _ = draw(s, 512, np.random.default_rng([args.seed, 3]), "train", args.frames,
                      args.noise_px)
        moving = moving_components(clean)
        sc = measure_scales(s, pts, moving)
        h, w = s.size
        print(f"[{name}] keypoint noise {args.noise_px} px: sd of d2 from it x "
              f"{math.sqrt(6) * args.noise_px / w:.2g}, y {math.sqrt(6) * args.noise_px / h:.2g}")
        out["scales"][name] = {"scales": sc,
                               "magnitudes": report_scales(name, clean, pts, moving, sc)}
        for v in args.variants:
            if (v == "c" and name == "spring") or (v == "d" and name != "pendulum"):
                continue
            out["runs"].append(run(name, v, args, sc))
            if args.json is not None:
                _write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
