"""Vid2Param on a system other than the ball: the network of a system's K tracked points and
P parameters, its stages, and the units of its answers.

:class:`methods.vid2param.Vid2Param` composes :class:`PointsModel` when its ``system`` is not
the ball (``methods.get("vid2param", system="pendulum")``). The model is the system's shipped
checkpoint (``SYSTEM_CHECKPOINTS``) or the ``checkpoint`` path given (a model trained for a
system a user registered included: ``sysid-bench train --system S``); where neither exists
:meth:`PointsModel.load` raises :class:`methods.NotAvailable` with the command that trains one.

The network gives the normalised posterior of the system's parameters (prior units) and of its
K points' positions (view units, ``extent``); the checkpoint's stages (``std_scale``) act on the
parameters as on the ball's; the forecast is the network's own latent rollout (the learned
prior, ``forecast="latent"``), decoded to metres, where the checkpoint trained it, and otherwise
the system's simulator run on the posterior's draws (``forecast="physics"``). :class:`PointsStream` runs it one frame at a
time.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sysid_bench.core.estimator import MAX_HORIZON, Forecast, Observation, Posterior, Stream

__all__ = ["PointsModel", "PointsStream", "SYSTEM_CHECKPOINTS", "train_command"]

_CKPT_DIR = Path(__file__).resolve().parent / "checkpoints"
#: Where each shipped system's model lives (whether or not this checkout has it).
SYSTEM_CHECKPOINTS = {name: _CKPT_DIR / f"v2p_{name}.pt"
                      for name in ("pendulum", "spring", "collision")}


def train_command(system: str) -> str:
    """The one command that trains ``system``'s model from scratch."""
    return (f"sysid-bench train --system {system} --out runs/v2p_{system} "
            f"--export methods/vid2param/checkpoints/v2p_{system}.pt")


def physics_calibration_path(checkpoint) -> Path:
    """Where ``vid2param-physics``' std factors for ``checkpoint`` are kept: beside it,
    ``<stem>_physics.json``."""
    p = Path(checkpoint)
    return p.with_name(p.stem + "_physics.json")


#: ``vid2param-physics``'s fit on a system's network track (:meth:`PointsModel.physics_prefixes`):
#: the cross-entropy search's simulations and rounds, the distinct starts it hands to least
#: squares besides the network's own answer, and evaluations per least-squares run (lsq's
#: defaults but for two starts fewer: the network's answer is usually the best of them)
PHYSICS_FIT = (2000, 4, 3, 100)


class PointsModel:
    """A system's Vid2Param network and stages, loaded for a :class:`Vid2Param` (``est``).

    The estimator's ``system``, ``checkpoint``, ``device`` and ``threads`` choose what is
    loaded (``est`` drops this model when one of them changes); ``n_samples``, ``seed`` and
    ``clip`` are read from it at every answer.
    """

    def __init__(self, est):
        self._est = est
        self._load()

    # -- loading ------------------------------------------------------------------------------
    def _load(self) -> None:
        from methods import NotAvailable
        from sysid_bench.core import systems

        est = self._est
        sys_ = systems.get(est.system)
        from methods.vid2param import presets

        if presets.space_of(sys_.name) != presets.VIEW:
            raise ValueError("system: expected a system other than 'ball' (the ball's Vid2Param "
                             "runs the ball's own model)")
        if est.checkpoint is None:
            path = SYSTEM_CHECKPOINTS.get(sys_.name)
            if path is None:  # a system registered by a user: its model is theirs to give
                raise NotAvailable(
                    f"system: 'vid2param' is n/a on the {sys_.name} system: no model is shipped "
                    f"for it (pass checkpoint=F, a Vid2Param model trained for {sys_.name}: "
                    f"`sysid-bench train --system {sys_.name} --out runs/v2p_{sys_.name} "
                    f"--export F`)")
            if not path.is_file():
                raise NotAvailable(
                    f"system: 'vid2param' is n/a on the {sys_.name} system: no model is shipped "
                    f"for it (no Vid2Param model is shipped for {sys_.name}; train one with "
                    f"`{train_command(sys_.name)}`)")
        else:  # a shipped checkpoint's name (a condition model's) or a path
            from methods.vid2param.checkpoint import checkpoint_path

            path = checkpoint_path(est.checkpoint)
        import torch

        from methods.vid2param.checkpoint import build_net, load_checkpoint
        from methods.vid2param.inference import resolve_device, stream_device
        from methods.vid2param.stages import Pipeline

        ck = load_checkpoint(path)
        net = build_net(ck, path)
        if net.config.system != sys_.name:
            raise ValueError(f"checkpoint: {str(path)!r} was trained for the "
                             f"{net.config.system} system, not {sys_.name}")
        if est.threads is not None:  # the benchmark's thread count, as on the ball
            torch.set_num_threads(int(est.threads))
        self._dev = resolve_device(est.device)
        # a stream of single frames: "auto" means the CPU (launch- and copy-bound on a GPU)
        self._stream_dev = stream_device(est.device)
        self._net = net.to(self._dev).eval()
        self._pipeline = Pipeline.from_checkpoint(ck, path, net)
        self._sys = sys_
        self.path = path
        self.info = {k: ck.get(k) for k in ("train", "git_commit", "val_metrics",
                                            "source_sha256")}
        c = net.config
        self._pidx = [c.targets.index(p) for p in c.params]
        self._xidx = [c.targets.index(p) for p in c.positions]
        missing = [p for p in sys_.params if p not in c.params]
        if missing:
            raise ValueError(f"checkpoint: {str(path)!r} does not identify {missing}")
        # parameters in the system's order
        self._order = [list(c.params).index(p) for p in sys_.params]
        # the prior's bounds and the view's extent as arrays, once (a stream reads them every
        # push); read-only, as they are shared by every posterior
        self._lo, self._hi = sys_.prior_lo, sys_.prior_hi
        self._width = self._hi - self._lo
        x0, x1, y0, y1 = sys_.extent
        self._ext_scale, self._ext_shift = np.array([x1 - x0, y1 - y0]), np.array([x0, y0])
        for a in (self._lo, self._hi, self._width, self._ext_scale, self._ext_shift):
            a.setflags(write=False)

    @property
    def _torch(self):
        """torch, imported where used: a module held as an attribute cannot be deep-copied
        (the harness copies a fitted estimator per case)."""
        import torch

        return torch

    @property
    def frame_size(self) -> tuple[int, int]:
        """(H, W) the system's model takes."""
        return tuple(self._net.config.frame_size)

    # -- units ----------------------------------------------------------------------------------
    def _points(self, mu_pos: np.ndarray) -> np.ndarray:
        """Normalised positions (..., 2K) to metres (..., K, 2)."""
        p = mu_pos.reshape(*mu_pos.shape[:-1], -1, 2)
        if p.dtype == np.float64:  # x0 + (x1 - x0) x, y0 + (y1 - y0) y: the same two operations
            return p * self._ext_scale + self._ext_shift
        x0, x1, y0, y1 = self._sys.extent
        xs = x0 + (x1 - x0) * p[..., 0]
        out = np.empty(p.shape, xs.dtype)  # np.stack's numbers, at a third of its cost
        out[..., 0] = xs
        out[..., 1] = y0 + (y1 - y0) * p[..., 1]
        return out

    def _frames(self, frames) -> np.ndarray:
        fr = np.asarray(frames)
        if fr.ndim != 4 or tuple(fr.shape[-2:]) != tuple(self._net.config.frame_size):
            raise ValueError(f"frames: expected (N, T, H, W) with H x W = "
                             f"{tuple(self._net.config.frame_size)} (the {self._sys.name} "
                             f"model's size), got shape {fr.shape}")
        return fr

    def _obs_frames(self, obs: Observation) -> np.ndarray:
        if not isinstance(obs, Observation) or obs.frames is None:
            raise ValueError("obs: expected an Observation with frames (vid2param reads video)")
        return self._frames(np.asarray(obs.frames)[None])

    def _params(self, m: np.ndarray, s: np.ndarray, extras: dict, key: int,
                lazy: bool = False) -> Posterior:
        """Posterior of normalised mean and std (P,) in the network's order; ``lazy`` (a
        stream's push): its samples drawn when first read, the same bytes
        (:class:`methods.vid2param.fast.LazyPosterior`)."""
        est = self._est
        lo, hi, w = self._lo, self._hi, self._width
        m, s = m[self._order], s[self._order]
        # np.clip's numbers (NaN kept), without its Python wrapper's cost
        mean = lo + w * (np.minimum(np.maximum(m, 0.0), 1.0) if est.clip else m)
        std = w * s
        if lazy and est.n_samples:
            from methods.vid2param.fast import LazyPosterior

            return LazyPosterior(mean, std, {"n_simulations": 0, **extras}, loc=mean,
                                 seed=(int(est.seed), int(key)), n_samples=int(est.n_samples),
                                 bounds=(lo, hi) if est.clip else None, system=self._sys.name)
        samples = None
        if est.n_samples:
            rng = np.random.default_rng([int(est.seed), int(key)])
            samples = mean + std * rng.standard_normal((int(est.n_samples), len(mean)))
            if est.clip:
                samples = np.clip(samples, lo, hi)
        return Posterior(mean=mean, std=std, samples=samples,
                         extras={"n_simulations": 0, **extras}, system=self._sys.name)

    def posteriors(self, frames) -> tuple[np.ndarray, np.ndarray, np.ndarray, object]:
        """Every frame's normalised parameter posterior (N, T, P) (network order) after the
        stages, the network's points (N, T, K, 2) m, and the recurrent state after the last."""
        from methods.vid2param.inference import system_posteriors

        return system_posteriors(self._net, self._pipeline.stages, self._frames(frames),
                                 self._dev, self._sys.extent)

    # -- the estimator --------------------------------------------------------------------------
    def identify(self, obs: Observation) -> Posterior:
        t0 = time.perf_counter()
        m, s, pts, _ = self.posteriors(self._obs_frames(obs))
        return self._params(m[0, -1], s[0, -1], {"wall_s": time.perf_counter() - t0,
                                                 "n_frames": m.shape[1]}, m.shape[1])

    def _prefix_pass(self, obs: Observation, lengths):
        """One network pass over ``obs`` for the prefixes ``lengths`` (checked): the frames
        (1, T, H, W), the lengths, :meth:`posteriors`' outputs and the pass's seconds."""
        fr = self._obs_frames(obs)
        T = fr.shape[1]
        lengths = [int(n) for n in np.atleast_1d(lengths)]
        if not lengths or min(lengths) < 1 or max(lengths) > T:
            raise ValueError(f"lengths: expected frame counts in [1, {T}], got {lengths}")
        t0 = time.perf_counter()
        out = self.posteriors(fr)
        return fr, lengths, out, time.perf_counter() - t0

    def identify_prefixes(self, obs: Observation, lengths) -> list[Posterior]:
        fr, lengths, (m, s, _, _), wall = self._prefix_pass(obs, lengths)
        T = fr.shape[1]
        return [self._params(m[0, n - 1], s[0, n - 1], {"wall_s": wall * n / T, "n_frames": n},
                             n) for n in lengths]

    def identify_batch(self, frames) -> list[Posterior]:
        """``identify`` of each of many videos (N, T, H, W), one network pass."""
        m, s, _, _ = self.posteriors(frames)
        return [self._params(m[i, -1], s[i, -1], {"n_frames": m.shape[1]}, m.shape[1])
                for i in range(len(m))]

    def _rollout(self, state, horizon: int) -> Forecast:
        horizon = int(horizon)
        if not 1 <= horizon <= MAX_HORIZON:
            raise ValueError(f"horizon: expected an int in [1, {MAX_HORIZON}], got {horizon}")
        torch = self._torch
        with torch.inference_mode():
            mu, std, _ = self._net.rollout(state, horizon)
        mu, std = mu[0].cpu().numpy().astype(np.float64), std[0].cpu().numpy().astype(np.float64)
        mean = self._points(mu[:, self._xidx])  # (H, K, 2)
        x0, x1, y0, y1 = self._sys.extent
        sd = std[:, self._xidx].reshape(horizon, -1, 2) * np.array([x1 - x0, y1 - y0])
        if self._sys.n_points == 1:
            mean, sd = mean[:, 0], sd[:, 0]
        return Forecast(mean=mean, std=sd, extras={"n_simulations": 0, "forecast": "latent"})

    @property
    def latent_learnt(self) -> bool:
        """Whether the checkpoint's latent forecast was trained: a run of the points curriculum
        alone (``points_steps >= steps``) never trains the conv encoder, prior and decoder that
        the latent rollout runs through."""
        tr = self.info.get("train") or {}
        return int(tr.get("points_steps") or 0) < int(tr.get("steps") or 0) or not tr

    def forecast_kind(self, kind: str | None = None) -> str:
        """``kind``, else the estimator's ``forecast``, else the latent rollout where the
        checkpoint trained it and the simulator otherwise."""
        kind = kind or getattr(self._est, "forecast_kind", None)
        return kind or ("latent" if self.latent_learnt else "physics")

    def forecast(self, obs: Observation, horizon: int, kind: str | None = None) -> Forecast:
        """Points after the observed frames: (H, 2) for one tracked point, (H, K, 2) for K > 1,
        metres. ``kind`` ``"latent"``: the network's latent rollout; ``"physics"``: the
        system's simulator run on draws of the posterior from the state that, with the
        posterior mean, best explains the observed track. None: the latent rollout where the
        checkpoint trained it (:attr:`latent_learnt`), the simulator otherwise."""
        if self.forecast_kind(kind) == "physics":
            return self._physics_forecast(obs, horizon)
        _, _, _, state = self.posteriors(self._obs_frames(obs))
        return self._rollout(state, horizon)

    def _physics_forecast(self, obs: Observation, horizon: int,
                          post: Posterior | None = None) -> Forecast:
        from methods._points import Points, default_sigma, forecast_points, refine

        horizon = int(horizon)
        if not 1 <= horizon <= MAX_HORIZON:
            raise ValueError(f"horizon: expected an int in [1, {MAX_HORIZON}], got {horizon}")
        t0 = time.perf_counter()
        if post is None:  # a stream passes the posterior it already has
            post = self.identify(obs)
        sys_, est = self._sys, self._est
        lo, hi = sys_.prior_lo, sys_.prior_hi
        mean = np.clip(post.mean, lo, hi)
        # the state is fitted with the parameters held at the posterior mean (the track's own
        # tracker, as every simulation method reads the frames)
        prob = Points(sys_, default_sigma(sys_), known=dict(zip(sys_.params, mean))).problem(obs)
        if prob.free:
            u0 = np.r_[np.full(prob.P, 0.5), prob.u_state0]
            u, _, _ = refine(prob, [u0], max_evals=200)
        else:
            u = np.full(prob.P, 0.5)
        _, s0 = prob.split(u)
        n = max(int(est.n_samples or 0), 32)
        rng = np.random.default_rng([int(est.seed), 1, int(prob.track.n_frames)])
        theta = np.clip(mean + post.std * rng.standard_normal((n, len(mean))), lo, hi)
        theta[0] = mean
        fc = forecast_points(prob.sim, sys_, theta, np.broadcast_to(s0, (n, prob.S)),
                             prob.track.n_frames, prob.track.dt, horizon,
                             {"forecast": "physics", "state_fit_rms_m": prob.rms(u)})
        fc.extras["wall_s"] = time.perf_counter() - t0
        return fc

    def stream(self) -> PointsStream:
        return PointsStream(self)

    # -- vid2param-physics: the system's physics fitted to the network's track ---------------
    def physics_scale(self) -> tuple[np.ndarray, str]:
        """``vid2param-physics``' std factors (P,) in the system's order and where they come
        from: the calibration file beside the checkpoint (:func:`physics_calibration_path`,
        written by ``scripts/calibrate_v2p_physics.py``) when it was made for this
        checkpoint's bytes; ones otherwise (a model nobody calibrated: the answer says so)."""
        cached = getattr(self, "_physics_scale", None)
        if cached is not None:
            return cached
        import hashlib
        import json

        P = len(self._sys.params)
        cal = physics_calibration_path(self.path)
        out = (np.ones(P), "none: no calibration for this checkpoint")
        if cal.is_file():
            try:
                rec = json.loads(cal.read_text())
                sha = hashlib.sha256(Path(self.path).read_bytes()).hexdigest()
                if rec.get("checkpoint_sha256") == sha:
                    f = np.array([float(rec["std_scale"][q]) for q in self._sys.params])
                    if np.isfinite(f).all() and (f >= 1.0).all():
                        out = (f, cal.name)
                else:
                    out = (np.ones(P), f"none: {cal.name} was made for another checkpoint")
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise ValueError(f"{cal}: expected vid2param-physics' calibration (JSON with "
                                 f"checkpoint_sha256 and std_scale), could not read it: "
                                 f"{exc}") from None
        self._physics_scale = out
        return out

    def physics_prefixes(self, obs: Observation, lengths,
                         calibrated: bool = True) -> list[Posterior]:
        """``vid2param-physics`` on this system: after each of ``lengths`` frames, the system's
        physics fitted to the network's own track of the first n frames (one network pass).

        The network reads its K points in every frame and its posterior over the parameters;
        the fit (:mod:`methods._points`: lsq's cross-entropy search, then least squares from
        the network's answer and the search's best distinct points) finds the parameters and
        initial state of one simulated trajectory through that track. Spread: its Laplace
        approximation, widened for a track that errs by more than the noise or in runs of
        frames (:func:`methods._points.noise_inflation`: the network's misreadings are not
        white). The model check judges the fitted trajectory against the frames' own track
        (``System.track``, as every simulation method reads the frames: the network's track
        follows whatever the network reads), over the same n frames; a failed check widens
        the intervals to the prior. Where the frames' tracker sees the points in fewer than 3
        of them, the check reads the network's track and says so. ``calibrated=False``: the
        spread without the calibration's factors (what the calibration itself fits).
        """
        import dataclasses

        from methods._points import (
            Points,
            PointsSimulator,
            Problem,
            answer_prior,
            default_sigma,
            draw_inside,
            noise_inflation,
            prepare_points,
            refine,
            search,
            uninformed_params,
        )

        est, sys_ = self._est, self._sys
        fr, lengths, (m, s, pts, _), wall = self._prefix_pass(obs, lengths)
        T = fr.shape[1]
        sigma = default_sigma(sys_)
        part = Points(sys_, sigma, min_frames=3, seed=est.seed)
        try:  # the frames' own track, for the model check
            seen = prepare_points(Observation(frames=fr[0], dt=obs.dt, scene=obs.scene,
                                              system=sys_.name), sys_, 1)
        except ValueError:  # not seen in any frame
            seen = None
        n_search, rounds, n_starts, max_evals = PHYSICS_FIT
        out = []
        for n in lengths:
            t1 = time.perf_counter()
            net = self._params(m[0, n - 1], s[0, n - 1], {}, n)
            track = Observation(positions=pts[0, :n], dt=obs.dt, scene=obs.scene,
                                system=sys_.name)
            prob = part.problem(track)
            rng = np.random.default_rng([int(est.seed), 17, n])
            starts, info = search(prob, rng, n_search, rounds, n_starts)
            u_net = np.clip((net.mean - prob.plo) / prob.pspan, 0.0, 1.0)
            if prob.free:
                u_net = np.r_[u_net, prob.u_state0]
            u, cov, opt = refine(prob, [u_net, *starts], max_evals)
            theta, s0 = prob.split(u)
            # a parameter the track does not inform (at 50 frames the collision's carts may not
            # have met a wall yet) answers the prior's centre and spread, not the optimiser's point
            flat = uninformed_params(prob, cov)
            res = prob.point_residuals(theta, s0)
            k, spread = noise_inflation(prob, res=res)
            cov = cov * k**2
            std = np.minimum(np.sqrt(np.diag(cov)[:prob.P]), np.sqrt(1.0 / 12.0)) * prob.pspan
            # n_samples 0: no samples in the answer (50 drawn for a widened one's shape)
            draws = draw_inside(u, cov, int(est.n_samples or 0) or 50, rng)
            th_d, _ = prob.split(draws)
            # the calibration's factors (90% intervals holding 90% of train videos' truths):
            # the network's track errs by a bias no noise model holds (the pendulum's bob
            # centroid ~2 mm towards the pivot: L ~2 of its Laplace stds short)
            fac, fac_source = (self.physics_scale() if calibrated
                               else (np.ones(prob.P), "none: calibrated=False"))
            std = np.minimum(std * fac, prob.pspan / np.sqrt(12.0))
            th_d = np.clip(theta + fac * (th_d - theta), prob.plo, prob.plo + prob.pspan)
            mean = theta.copy()
            answer_prior(prob, flat, mean, std, th_d, rng)
            sims = prob.sim.n_simulations
            ok = seen is not None and int(seen.mask[:n].any(axis=1).sum()) >= 3
            if ok:
                own = dataclasses.replace(seen, positions=seen.positions[:n],
                                          mask=seen.mask[:n])
                cprob = Problem(own, sigma, PointsSimulator(sys_))
                check = cprob.check(theta, s0)
                sims += cprob.sim.n_simulations
            else:
                check = prob.check(theta, s0, "checked against the network's own track: the "
                                   "frames' tracker sees the points in fewer than 3 frames",
                                   res=res)
            extras = {"wall_s": wall * n / T + time.perf_counter() - t1, "n_frames": n,
                      "n_simulations": sims, "network_mean": net.mean.tolist(),
                      "network_std": net.std.tolist(), "track_rms_m": prob.rms(u),
                      "state0": s0.tolist(), "fit_theta": theta.tolist(),
                      "uninformed": [q for q, f in zip(sys_.params, flat) if f],
                      "physics_calibration": fac_source,
                      **spread, **info, **opt}
            post = part.posterior(prob, mean, std, th_d, extras, check)
            if not est.n_samples:
                post.samples = None
            out.append(post)
        return out


class _StreamHead:
    """What a push does after the NumPy filter, on Python floats: the network's points in
    metres, the stages' std factors, the clip to the prior and the posterior's checks
    (:meth:`LazyPosterior.from_floats <methods.vid2param.fast.LazyPosterior.from_floats>`).

    The same IEEE double operations, one element at a time and in the same order, as
    :meth:`PointsModel._points`, ``Pipeline.step`` and :meth:`PointsModel._params` on arrays
    of 2K and P elements -- each of those numpy calls costs microseconds of overhead on 4
    numbers. ``weak_evidence`` stages before the ``std_scale`` ones run as ``Pipeline.step``
    runs them (their compiled statistic, then the blend on arrays). :meth:`of` gives None (the
    array path runs) for a pipeline with any other stage that changes the posterior; a system
    that overrides ``check_posterior_mean`` has its posteriors built by the ordinary
    constructor. Built at
    each :meth:`PointsStream.reset` (the stages it read then).
    """

    def __init__(self, model: PointsModel, factors: list[list[float]], weak=()):
        from sysid_bench.core.systems import System

        sys_ = model._sys
        self.xidx = list(model._xidx)
        self.pidx = list(model._pidx)
        # the weak_evidence stages (before every std_scale) and their index in the pipeline:
        # run on arrays, as Pipeline.step runs them
        self.weak = list(weak)
        # per parameter in the system's order: its index in what posterior() reads (the latent;
        # with weak stages, the network's parameters after them) and its stage factors
        latent = [model._pidx[k] for k in model._order] if not self.weak else list(model._order)
        self.factors = [[f[k] for f in factors] for k in model._order]
        self.bounds = (model._lo, model._hi)  # the samples' clip, the arrays _params passes
        self.scale, self.shift = model._ext_scale.tolist(), model._ext_shift.tolist()
        self.system = sys_.name
        self.mean_bounds = ([tuple(map(float, b)) for b in sys_._mean_bounds()]
                            if type(sys_).check_posterior_mean is System.check_posterior_mean
                            else None)
        self.plan = list(zip(latent, self.factors, model._lo.tolist(), model._width.tolist()))
        from methods.vid2param.fast import LazyPosterior

        self.lazy = LazyPosterior

    @classmethod
    def of(cls, model: PointsModel) -> _StreamHead | None:
        """The head of ``model``'s pipeline, or None where the array path must run."""
        from methods.vid2param.stages import Stage, StdScale, WeakEvidence

        factors, weak = [], []
        for k, st in enumerate(model._pipeline.stages):
            if type(st) is StdScale:
                factors.append([float(f) for f in st.factors])  # the network's order
            elif type(st) is WeakEvidence and not factors:
                weak.append((k, st))
            elif type(st).step is not Stage.step:  # a stage that changes the posterior
                return None
        return cls(model, factors, weak)

    def points(self, mu: list[float]) -> np.ndarray:
        """The network's points (K, 2) m from the latent ``mu`` (floats): ``_points``' x0 +
        (x1 - x0) x, y0 + (y1 - y0) y, as the float64 path computes them."""
        (sx, sy), (x0, y0), ix = self.scale, self.shift, self.xidx
        return np.array([[mu[ix[i]] * sx + x0, mu[ix[i + 1]] * sy + y0]
                         for i in range(0, len(ix), 2)])

    def posterior(self, mu: list[float], sd: list[float], wall_s: float, n: int, est,
                  carries=()):
        """``PointsModel._params(..., lazy=True)`` of the latent ``mu``, ``sd`` (floats) after
        the stages, after ``n`` frames (the samples' key), for an estimator ``est`` that draws
        samples (``n_samples`` 0: the array path answers with none); ``carries`` the stream's
        stage states (``Pipeline.start``), which the weak_evidence stages update."""
        clip = est.clip
        if self.weak:  # Pipeline.step's arrays, then floats in the network's parameter order
            m = np.array([[mu[i] for i in self.pidx]])
            s = np.array([[sd[i] for i in self.pidx]])
            pts = self.points(mu)[None]
            for k, stage in self.weak:
                m, s = stage.step(carries[k], m, s, pts)
            mu, sd = m[0].tolist(), s[0].tolist()
        mean, std = [], []
        for i, fs, lo, w in self.plan:
            m, s = mu[i], sd[i]
            for f in fs:  # StdScale.step: sd * factors
                s = s * f
            if clip:  # np.minimum(np.maximum(m, 0), 1): NaN stays NaN (and is refused)
                if m < 0.0:
                    m = 0.0
                elif m > 1.0:
                    m = 1.0
            mean.append(lo + w * m)
            std.append(w * s)
        return self.lazy.from_floats(
            mean, std, {"n_simulations": 0, "wall_s": wall_s, "n_frames": n},
            seed=(int(est.seed), n), n_samples=int(est.n_samples),
            bounds=self.bounds if clip else None, system=self.system,
            mean_bounds=self.mean_bounds)


class PointsStream(Stream):
    """One frame at a time through the network and the stages (constant cost per frame).

    On the CPU a push runs :class:`methods.vid2param.fast.FrameFilter` (the ball stream's NumPy
    path: the same network, float32 rounding apart) where it supports the network; otherwise,
    and on an accelerator, the torch modules.
    """

    def __init__(self, model: PointsModel):
        self._est = model
        self._fast = None
        self.reset()

    def reset(self) -> None:
        import copy

        from methods.vid2param.fast import frame_filter_for

        dev = self._est._stream_dev
        net = self._est._net
        self._fast = frame_filter_for(net, dev, self._fast)
        if self._fast is None and dev.type != self._est._dev.type:
            # no NumPy filter for this network: the torch modules, copied to the stream's device
            net = copy.deepcopy(net).to(dev)
        self._net = net
        self._state = None if self._fast is not None else net.init_state(1, dev)
        self._carries = self._est._pipeline.start(1)
        # after the NumPy filter, the posterior head on Python floats where it covers the stages
        self._head = _StreamHead.of(self._est) if self._fast is not None else None
        self._n = 0
        self._pts = np.full((self._est._sys.n_points, 2), np.nan)
        # a simulator forecast reads the frames seen so far (the track it fits the state to)
        self._seen = [] if self._est.forecast_kind() == "physics" else None
        self._post = None  # the latest push's posterior

    @property
    def n_frames(self) -> int:
        return self._n

    def push(self, frame: np.ndarray) -> Posterior:
        est, torch = self._est, self._est._torch
        fr = np.asarray(frame)
        if tuple(fr.shape) != tuple(est._net.config.frame_size):
            raise ValueError(f"frame: expected shape {tuple(est._net.config.frame_size)}, got "
                             f"{fr.shape}")
        t0 = time.perf_counter()
        net = self._net
        head = self._head
        if head is not None and self._fast is not None and est._est.n_samples:
            # the NumPy filter, then the head on Python floats (the array path's numbers)
            mu, sd = self._fast.step(fr)
            mu, sd = mu.tolist(), sd.tolist()
            self._n += 1
            self._pts, self._mu = None, (head, mu)  # points made when position() reads them
            if self._seen is not None:
                self._seen.append(fr.copy())
            self._post = head.posterior(mu, sd, time.perf_counter() - t0, self._n, est._est,
                                        self._carries)
            return self._post
        if self._fast is not None:
            mu, sd = self._fast.step(fr)
            mu, sd = mu[None].astype(np.float64), sd[None].astype(np.float64)
        else:
            with torch.inference_mode():
                fx = net.encode_frames(torch.as_tensor(fr[None], device=est._stream_dev))
                mu, sd = net.enc_step(fx, net.read(self._state))
                self._state = net.step_rnn(mu, self._state)
            mu = mu.cpu().numpy().astype(np.float64)
            sd = sd.cpu().numpy().astype(np.float64)
        pts = est._points(mu[:, est._xidx])
        m, s = est._pipeline.step(self._carries, mu[:, est._pidx], sd[:, est._pidx], pts)
        self._n += 1
        self._pts = pts[0]
        if self._seen is not None:
            self._seen.append(fr.copy())
        self._post = est._params(m[0], s[0], {"wall_s": time.perf_counter() - t0,
                                              "n_frames": self._n}, self._n, lazy=True)
        return self._post

    def position(self) -> np.ndarray:
        """The network's first tracked point (2,) m at the latest frame."""
        if self._pts is None:
            head, mu = self._mu
            self._pts = head.points(mu)
        return self._pts[0].copy()

    def forecast(self, horizon: int, floor: float | None = None) -> Forecast:
        if self._seen is not None:
            if not self._seen:
                raise ValueError("forecast: expected at least one pushed frame, got none")
            obs = Observation(frames=np.stack(self._seen), system=self._est._sys.name)
            fc = self._est._physics_forecast(obs, horizon, self._post)
            if floor:
                fc.mean[..., 1] += float(floor)
            return fc
        dev = self._est._dev  # the rollout runs on the model's device
        state = (self._fast.torch_state(dev) if self._fast is not None
                 else self._state.map(lambda t: t.to(dev)))
        fc = self._est._rollout(state, horizon)
        if floor:
            fc.mean[..., 1] += float(floor)
        return fc
