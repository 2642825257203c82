"""The stages after Vid2Param's network: named, ordered, fitted on training videos.

Vid2Param is a network followed by an ordered list of stages. Each stage is fitted once the
network is trained (``fit``: on train-split videos, the network frozen, the stages before it in
place), and answers in batch (``apply``: every frame of many videos) and streaming
(``start``, then ``step`` per frame) alike; one loop (:class:`Pipeline`) runs them for both.
A checkpoint stores them in order as ``checkpoint["stages"]``, each ``{"name": ..., "state":
{...}}`` (its fitted numbers and the record of its fit).

Stages read and write named quantities. The network gives ``theta`` (the normalised posterior
of ``PARAMS``, (..., 4) mean and std), ``track`` (its positions, metres) and, with
``config.physics_prior``, ``physics_prior`` (the latent rollout's transition). A stage
``needs`` some and ``gives`` some; a stage list whose stage needs a quantity nothing before it
gives is refused, as is an unknown stage: ``ValueError`` naming the checkpoint and the stage.

======================  =========================  =========================================
stage                   needs -> gives             what it is
======================  =========================  =========================================
``std_scale``           theta -> theta             one std factor per parameter (intervals
                                                   hold 90% on train videos)
``prior_noise``         physics_prior, theta,      the physics prior's process noise
                        track -> forecast_noise    (``fit_prior``): acts on forecasts
``drag_evidence``       theta, track -> theta      the drag constant read off the track and
                                                   blended into d (``drag``; ball-specific)
``physics_calibration`` theta, track ->            ``vid2param-physics``'s std factors
                        physics_scale              (``calibrate_physics``)
``weak_evidence``       theta, track -> theta      a system's damping read off the track by a
                                                   weak-form least-squares fit and blended in
                                                   (``weak_evidence``; pendulum, spring,
                                                   collision)
======================  =========================  =========================================

Which stages a model gets is its system's configuration (``presets.Preset.stages``): the drag
evidence reads a flying ball's track. The rolling statistic is not a stage: it is part of the
network (its features feed the heads, which were trained with them; ``V2PConfig.roll_stat``).

Checkpoints written before stages existed keep their fits under ``calibration``,
``prior_fit``, ``drag_evidence`` and ``physics_calibration``; :meth:`Pipeline.from_checkpoint`
converts them on load (``LEGACY_KEYS``, in the order their fits ran), with the same numbers.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from methods.vid2param import presets
from methods.vid2param.drag import DragBlend, DragStatistic, statistic_track
from methods.vid2param.inference import param_index, positions
from sysid_bench.core.physics import PARAMS

__all__ = ["Stage", "STAGES", "register_stage", "Pipeline", "StdScale", "PriorNoise",
           "DragEvidence", "PhysicsCalibration", "WeakEvidence", "LEGACY_KEYS",
           "network_gives", "describe"]

#: Registered stages by name (:func:`register_stage`).
STAGES: dict[str, type[Stage]] = {}


def register_stage(cls: type[Stage]) -> type[Stage]:
    """Add a stage class to ``STAGES`` under its ``name`` (a class decorator)."""
    if not isinstance(getattr(cls, "name", None), str) or not cls.name:
        raise ValueError(f"stage: expected a class with a non-empty str name, got {cls!r}")
    if cls.name in STAGES and STAGES[cls.name] is not cls:
        raise ValueError(f"stage: {cls.name!r} is already registered ({STAGES[cls.name]})")
    STAGES[cls.name] = cls
    return cls


def network_gives(config) -> set[str]:
    """The quantities a network of ``config`` gives the stages."""
    return {"theta", "track"} | ({"physics_prior"} if config.physics_prior else set())


class Stage:
    """A stage after the network (see the module). Subclasses set ``name``, ``needs``,
    ``gives`` and implement ``fit`` (a classmethod) and, where they change the parameter
    posterior, ``apply`` and ``step``; the default passes it through.

    Parameters
    ----------
    state : dict
        The fitted numbers and the record of the fit (stored in the checkpoint).
    source : str
        The checkpoint's name, for error messages.
    """

    name: str = ""
    needs: frozenset = frozenset()
    gives: frozenset = frozenset()
    #: the key a checkpoint of the older format keeps this stage's state under
    legacy_key: str | None = None

    def __init__(self, state: dict, source: str = "checkpoint"):
        if not isinstance(state, dict):
            raise ValueError(f"checkpoint {source}: stage {self.name!r} expected a dict state, "
                             f"got {type(state).__name__}")
        self.state = state
        self.source = source

    @classmethod
    def fit(cls, ctx, **options) -> Stage:
        """Fit on train videos (``ctx``: ``inference.FitContext``); returns the stage."""
        raise NotImplementedError

    @classmethod
    def fit_options(cls) -> tuple[str, ...]:
        """The names of the options :meth:`fit` takes (the driver's ``NAME:KEY=VALUE``): its
        named keywords; a stage whose ``fit`` passes ``**options`` on adds what they reach."""
        import inspect

        return tuple(n for n, p in inspect.signature(cls.fit).parameters.items()
                     if n != "ctx" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY))

    @classmethod
    def check_options(cls, options) -> None:
        """``ValueError`` naming the stage and every option of ``options`` that :meth:`fit`
        does not take (a misspelt option would otherwise be dropped or fail deep in a fit)."""
        known = cls.fit_options()
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise ValueError(f"stages: stage {cls.name!r} has no option "
                             f"{', '.join(map(repr, unknown))} (its options: "
                             f"{', '.join(known) or 'none'})")

    def bind(self, net) -> None:
        """Attach to the loaded network (a stage that owns some of its weights sets them)."""

    def apply(self, mu: np.ndarray, sd: np.ndarray, track: np.ndarray):
        """Batch: the normalised posterior ``mu``, ``sd`` (..., T, 4) after every frame, given
        the track (..., T, 2) m; returns the new ``mu``, ``sd``."""
        return mu, sd

    def start(self, batch: int):
        """Streaming: the state before the first frame of ``batch`` videos (None: stateless)."""
        return None

    def step(self, carry, mu: np.ndarray, sd: np.ndarray, pos: np.ndarray):
        """Streaming: ``apply`` for one frame, ``mu``, ``sd`` (B, 4), ``pos`` (B, 2) m, with
        ``carry`` from ``start`` (updated in place)."""
        return mu, sd

    def record(self) -> dict:
        """The checkpoint entry: ``{"name": ..., "state": ...}``."""
        return {"name": self.name, "state": self.state}

    def summary(self) -> str:
        """A few words on the fitted numbers, for ``describe``."""
        return ""


def _factors(state: dict, what: str, source: str, name: str) -> np.ndarray:
    """``PARAMS``' factors of a ``{"std_scale": [...], "targets": [...]}`` state (ones where a
    parameter has none); finite and > 0."""
    scale = dict(zip(state.get("targets", []), state.get("std_scale", [])))
    out = np.array([float(scale.get(p, 1.0)) for p in PARAMS])
    if not (np.isfinite(out).all() and (out > 0).all()):
        raise ValueError(f"checkpoint {source}: stage {name!r}: {what} factors must be finite "
                         f"and > 0, got {out}")
    return out


@register_stage
class StdScale(Stage):
    """One factor per parameter on the network's stds (``train.calibrate`` fits them so that
    90% intervals hold 90% of the truths on fresh train videos)."""

    name = "std_scale"
    needs = frozenset({"theta"})
    gives = frozenset({"theta"})
    legacy_key = "calibration"

    def __init__(self, state: dict, source: str = "checkpoint"):
        super().__init__(state, source)
        self.factors = _factors(state, "calibration", source, self.name)

    @classmethod
    def fit(cls, ctx, n: int = 500, seed: int = 424242) -> StdScale:
        """Factors from ``n`` clean train videos (``seed``), after their last frame (a system's
        train split for a system's network)."""
        from methods.vid2param.data import make_split, make_system_split

        n_fr = ctx.n_frames
        system = ctx.net.config.system
        # clean videos of the run's size and nuisances, not its variant (as the shipped fit)
        if presets.space_of(system) == presets.VIEW:
            ds = make_system_split(system, "train", int(n), int(seed), n_fr, ctx.frame_size,
                                   ctx.train.get("nuisance"), workers=ctx.train.get("threads", 1))
        else:
            ds = make_split("train", int(n), int(seed), ctx.frame_size,
                            ctx.train.get("nuisance"), n_fr)
        # at the full length, where the benchmark reports: measured on the shipped 28x28 model,
        # factors pooled over 50-200 frames (e 1.22) left e's 90% intervals holding 74% of the
        # test truths at 200 frames; earlier prefixes were already within 80-97%
        if ctx.pipeline.stages and presets.space_of(system) == presets.VIEW:
            # a system's stages before it (weak_evidence) change the posterior it scales
            factors = _system_factors(ctx, ds, n_fr)
        else:
            factors = calibrate(ctx.net, ds, lengths=(n_fr,))
        return cls({"std_scale": factors.tolist(), "targets": list(ctx.net.config.targets),
                    "n": int(n), "seed": int(seed), "split": "train", "level": 0.9,
                    "lengths": [n_fr]}, ctx.source)

    def bind(self, net) -> None:
        # a system's network: one factor per parameter of its own (in its targets' order)
        if presets.space_of(net.config.system) == presets.VIEW:
            scale = dict(zip(self.state.get("targets", []), self.state.get("std_scale", [])))
            self.params = tuple(net.config.params)
            self.factors = np.array([float(scale.get(p, 1.0)) for p in self.params])

    def apply(self, mu, sd, track):
        return mu, sd * self.factors

    def step(self, carry, mu, sd, pos):
        return mu, sd * self.factors

    def summary(self) -> str:
        names = getattr(self, "params", PARAMS)
        return "x(" + ", ".join(f"{p} {f:.2f}" for p, f in zip(names, self.factors)) + ")"


def _system_factors(ctx, ds, n_fr: int, level: float = 0.9) -> np.ndarray:
    """``calibrate``'s factors (``config.targets`` order; 1 for the positions) for a system's
    network with the stages fitted so far in place, after frame ``n_fr``."""
    from scipy.stats import norm

    c = ctx.net.config
    m, s, _ = ctx.system_parameters(np.asarray(ds.frames))
    truth = ds.system.normalise(ds.theta)  # (N, P), the system's order
    tg = truth[:, [ds.system.params.index(p) for p in c.params]]
    z = np.abs(m[:, n_fr - 1] - tg) / s[:, n_fr - 1]
    q = np.quantile(z, level, axis=0) / norm.ppf(0.5 + level / 2)
    out = np.ones(len(c.targets))
    out[[c.targets.index(p) for p in c.params]] = q
    return out


@register_stage
class WeakEvidence(Stage):
    """A system's damping read off the network's track by a weak-form least-squares fit,
    blended into its posterior by inverse variance (``methods.vid2param.weak_evidence``)."""

    name = "weak_evidence"
    needs = frozenset({"theta", "track"})
    gives = frozenset({"theta"})

    def __init__(self, state: dict, source: str = "checkpoint"):
        super().__init__(state, source)
        from methods.vid2param.weak_evidence import WEAK_FORMS

        try:
            self.form = WEAK_FORMS[state["system"]]
            self.params = tuple(str(p) for p in state["params"])
            self.kappa = np.array([float(v) for v in state["kappa"]])
            self.tau = np.array([float(v) for v in state["tau"]])
            self.window, self.dt = int(state["window"]), float(state["dt"])
            self.gain = float(state.get("gain", 1.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"checkpoint {source}: stage {self.name!r}: expected a state with "
                             f"a system of {sorted(WEAK_FORMS)}, params, kappa, tau, window and "
                             f"dt, got {state!r:.200} ({exc!r})") from None
        if (self.params != tuple(self.form.blends) or len(self.kappa) != len(self.params)
                or len(self.tau) != len(self.params)
                or not (np.isfinite(self.kappa).all() and (self.kappa > 0).all()
                        and np.isfinite(self.tau).all() and (self.tau >= 0).all())
                or self.window < 2 or not (self.dt > 0)
                or not (np.isfinite(self.gain) and self.gain >= 0)):
            raise ValueError(f"checkpoint {source}: stage {self.name!r}: expected params "
                             f"{list(self.form.blends)} with kappa > 0 and tau >= 0 each, a "
                             f"window >= 2, dt > 0 and gain >= 0, got {state!r:.200}")

    @classmethod
    def fit(cls, ctx, n: int = 500, seed: int = 424243) -> WeakEvidence:
        """``kappa`` and ``tau`` of each parameter and the statistic's ``gain`` by the blended
        posterior's NLL on ``n`` clean train videos (``seed``) after 50, 100, 150 and 200
        frames."""
        from methods.vid2param.data import make_system_split
        from methods.vid2param.weak_evidence import GAINS, WEAK_FORMS, WINDOW, fit_blend

        system = ctx.net.config.system
        if system not in WEAK_FORMS:
            raise ValueError(f"stages: 'weak_evidence' has no weak form for the {system} system "
                             f"(it has one for {', '.join(sorted(WEAK_FORMS))})")
        form, dt = WEAK_FORMS[system], 0.05
        ds = make_system_split(system, "train", int(n), int(seed), ctx.n_frames, ctx.frame_size,
                               ctx.train.get("nuisance"), workers=ctx.train.get("threads", 1))
        m, s, pts = ctx.system_parameters(np.asarray(ds.frames))
        sys_ = ds.system
        truth = sys_.normalise(ds.theta)
        params = ctx.net.config.params
        best = None
        for gain in GAINS:
            est, var = form.track(pts, WINDOW, dt, gain)
            fits = []
            for j, p in enumerate(form.blends):
                i, k = params.index(p), sys_.params.index(p)
                lo, width = sys_.prior_lo[k], sys_.prior_hi[k] - sys_.prior_lo[k]
                fits.append(fit_blend(m[..., i], s[..., i], est[..., j], var[..., j],
                                      truth[:, k], lo, width,
                                      unseen_prior=p in form.unseen_prior))
            total = sum(f[2] for f in fits)
            ctx.log(f"  gain {gain:g}: " + ", ".join(
                f"{p} kappa {f[0]:.3g} tau {f[1]:g} NLL {f[2]:.3f}"
                for p, f in zip(form.blends, fits)))
            if best is None or total < best[0]:
                best = (total, gain, fits)
        _, gain, fits = best
        return cls({"system": system, "params": list(form.blends),
                    "kappa": [f[0] for f in fits], "tau": [f[1] for f in fits],
                    "gain": gain, "window": WINDOW, "dt": dt, "nll": [f[2] for f in fits],
                    "n": int(n), "seed": int(seed), "split": "train",
                    "frames": [50, 100, 150, 200]}, ctx.source)

    def bind(self, net) -> None:
        from sysid_bench.core import systems

        c = net.config
        if c.system != self.form.system:
            raise ValueError(f"checkpoint {self.source}: stage {self.name!r} was fitted for the "
                             f"{self.form.system} system, the network is the {c.system}'s")
        sys_ = systems.get(c.system)
        k = [sys_.params.index(p) for p in self.params]
        self._idx = [list(c.params).index(p) for p in self.params]
        self._lo = sys_.prior_lo[k]
        self._width = sys_.prior_hi[k] - sys_.prior_lo[k]
        self._unseen = np.array([p in self.form.unseen_prior for p in self.params])

    def _blend(self, mu, sd, est, var):
        from methods.vid2param.weak_evidence import blend

        i = self._idx
        mu, sd = np.array(mu, dtype=np.float64), np.array(sd, dtype=np.float64)
        mu[..., i], sd[..., i] = blend(mu[..., i], sd[..., i], est, var, self._lo, self._width,
                                       self.kappa, self.tau, self._unseen)
        return mu, sd

    def apply(self, mu, sd, track):
        est, var = self.form.track(track, self.window, self.dt, self.gain)
        return self._blend(mu, sd, est, var)

    def start(self, batch: int):
        return self.form.statistic(batch, self.window, self.dt, self.gain)

    def step(self, carry, mu, sd, pos):
        carry.update(pos)
        return self._blend(mu, sd, *carry.summary())

    def summary(self) -> str:
        return "(" + ", ".join(f"{p} kappa {k:.2g} tau {t:g}" for p, k, t in
                               zip(self.params, self.kappa, self.tau)) + f"; gain {self.gain:g})"


@register_stage
class PriorNoise(Stage):
    """The physics prior's process noise (``methods.vid2param.fit_prior``): it shapes the
    latent forecasts' bands, not the parameter posterior. Its state holds the noise weights
    (``weights``), which it sets on the network when bound, and the fit's record."""

    name = "prior_noise"
    needs = frozenset({"physics_prior", "theta", "track"})
    gives = frozenset({"forecast_noise"})
    legacy_key = "prior_fit"

    @classmethod
    def fit_options(cls) -> tuple[str, ...]:
        from dataclasses import fields

        from methods.vid2param.fit_prior import PriorFitConfig

        return tuple(f.name for f in fields(PriorFitConfig))  # steps among them

    @classmethod
    def fit(cls, ctx, steps: int = 150, **options) -> PriorNoise:
        """Train the noise on the network's forecasts of train videos (``PriorFitConfig``;
        ``ctx.net`` is replaced by the network with the trained prior)."""
        from methods.vid2param.fit_prior import PriorFitConfig, fit_prior_stage

        cls.check_options(options)
        record, net = fit_prior_stage(ctx, PriorFitConfig(steps=int(steps), **options))
        ctx.net = net
        weights = {k: v.detach().cpu().clone() for k, v in net.phys_prior.state_dict().items()}
        return cls({"record": record, "weights": weights}, ctx.source)

    def bind(self, net) -> None:
        weights = self.state.get("weights")
        if weights is None:
            return
        if net.phys_prior is None:
            raise ValueError(f"checkpoint {self.source}: stage {self.name!r} needs a network "
                             "with a physics prior")
        try:
            net.phys_prior.load_state_dict(weights, strict=True)
        except (RuntimeError, TypeError) as exc:
            raise ValueError(f"checkpoint {self.source}: stage {self.name!r}: weights do not "
                             f"fit the physics prior ({str(exc)[:200]})") from exc

    def summary(self) -> str:
        rec = self.state.get("record") or {}
        cov = (rec.get("val_calibrated") or {}).get("cov90")
        return f"(validation cov90 {cov:.2f})" if cov is not None else ""


@register_stage
class DragEvidence(Stage):
    """The drag constant read off the track, blended into d (``methods.vid2param.drag``)."""

    name = "drag_evidence"
    needs = frozenset({"theta", "track"})
    gives = frozenset({"theta"})
    legacy_key = "drag_evidence"

    def __init__(self, state: dict, source: str = "checkpoint"):
        super().__init__(state, source)
        try:
            self.blend = DragBlend.from_record(state)
        except ValueError as exc:
            raise ValueError(f"checkpoint {source}: stage {self.name!r}: {exc}") from None
        if self.blend is None:
            raise ValueError(f"checkpoint {source}: stage {self.name!r} has an empty state")
        self._i = PARAMS.index("d")

    @classmethod
    def fit_options(cls) -> tuple[str, ...]:
        from dataclasses import fields

        from methods.vid2param.drag import DragFitConfig

        return tuple(f.name for f in fields(DragFitConfig))  # n_videos among them

    @classmethod
    def fit(cls, ctx, n_videos: int = 300, **options) -> DragEvidence:
        from methods.vid2param.drag import DragFitConfig, fit_drag_stage

        cls.check_options(options)
        return cls(fit_drag_stage(ctx, DragFitConfig(n_videos=int(n_videos), **options)),
                   ctx.source)

    def apply(self, mu, sd, track):
        T = track.shape[-2]
        D, S = statistic_track(track.reshape(-1, T, 2), self.blend.k)
        i, lead = self._i, (*mu.shape[:-1], 2)
        mu[..., i], sd[..., i] = self.blend.apply(mu[..., i], sd[..., i], D.reshape(lead),
                                                  S.reshape(lead))
        return mu, sd

    def start(self, batch: int):
        return DragStatistic(batch, self.blend.k)

    def step(self, carry, mu, sd, pos):
        carry.update(pos)
        D, S = carry.summary()
        i = self._i
        mu[:, i], sd[:, i] = self.blend.apply(mu[:, i], sd[:, i], D, S)
        return mu, sd

    def summary(self) -> str:
        return f"(k {self.blend.k})"


@register_stage
class PhysicsCalibration(Stage):
    """``vid2param-physics``'s std factors (``methods.vid2param.calibrate_physics``): they
    scale the covariance of the physics fitted to the track, not the network's posterior."""

    name = "physics_calibration"
    needs = frozenset({"theta", "track"})
    gives = frozenset({"physics_scale"})
    legacy_key = "physics_calibration"

    def __init__(self, state: dict, source: str = "checkpoint"):
        super().__init__(state, source)
        self.factors = _factors(state, "physics_calibration", source, self.name)

    @classmethod
    def fit_options(cls) -> tuple[str, ...]:
        import inspect

        from methods.vid2param.calibrate_physics import calibrate_physics_stage

        return tuple(n for n in inspect.signature(calibrate_physics_stage).parameters
                     if n != "ctx")

    @classmethod
    def fit(cls, ctx, n: int = 100, **options) -> PhysicsCalibration:
        from methods.vid2param.calibrate_physics import calibrate_physics_stage

        cls.check_options(options)

        return cls(calibrate_physics_stage(ctx, n=int(n), **options), ctx.source)

    def summary(self) -> str:
        return "x(" + ", ".join(f"{p} {f:.2f}" for p, f in zip(PARAMS, self.factors)) + ")"


#: Checkpoints of the older format: the key of each stage's state, in the order the fits ran
#: (``train.export_with_prior`` then the separate drag and physics-calibration commands).
LEGACY_KEYS = ("calibration", "prior_fit", "drag_evidence", "physics_calibration")

class Pipeline:
    """The ordered stages after a network; one loop for batch and stream.

    Parameters
    ----------
    stages : sequence of Stage
    """

    def __init__(self, stages: Sequence[Stage] = ()):
        self.stages = list(stages)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.stages]

    def get(self, name: str) -> Stage | None:
        """The stage called ``name``, or None."""
        return next((s for s in self.stages if s.name == name), None)

    def records(self) -> list[dict]:
        """``checkpoint["stages"]``."""
        return [s.record() for s in self.stages]

    @staticmethod
    def check(names: Sequence[str], config, source: str = "checkpoint") -> None:
        """Refuse unknown or duplicated stages and stages whose inputs nothing before gives."""
        have = network_gives(config)
        seen = set()
        for k, name in enumerate(names):
            if name not in STAGES:
                raise ValueError(f"checkpoint {source}: stage {k} {name!r} is unknown "
                                 f"(known stages: {', '.join(sorted(STAGES))})")
            if name in seen:
                raise ValueError(f"checkpoint {source}: stage {k} {name!r} appears twice")
            seen.add(name)
            missing = STAGES[name].needs - have
            if missing:
                raise ValueError(
                    f"checkpoint {source}: stage {k} {name!r} needs {sorted(missing)}, which "
                    f"neither the network nor a stage before it gives (stages: {list(names)})")
            have |= STAGES[name].gives

    @classmethod
    def from_checkpoint(cls, ck: dict, source, net) -> Pipeline:
        """The stages of a loaded checkpoint, checked and bound to its network ``net``.

        ``ck["stages"]`` when present; otherwise the older format's keys (``LEGACY_KEYS``)
        converted, with the ``physics_prior`` noise weights of the network as the
        ``prior_noise`` stage's. Never skips a stage: anything it cannot build is a
        ``ValueError`` naming the checkpoint and the stage.
        """
        source = str(source)
        if "stages" in ck:
            both = [k for k in LEGACY_KEYS if ck.get(k)]
            if both:
                raise ValueError(f"checkpoint {source}: holds stages and the older format's "
                                 f"{both} beside them; one or the other")
            entries = ck["stages"]
            if not isinstance(entries, (list, tuple)) or not all(
                    isinstance(e, dict) and isinstance(e.get("name"), str) for e in entries):
                raise ValueError(f"checkpoint {source}: stages: expected a list of "
                                 f"{{'name': str, 'state': dict}}, got {entries!r:.200}")
        else:
            entries = legacy_stages(ck, net)
        names = [e["name"] for e in entries]
        cls.check(names, net.config, source)
        stages = [STAGES[e["name"]](e.get("state"), source) for e in entries]
        for s in stages:
            s.bind(net)
        return cls(stages)

    def apply(self, mu: np.ndarray, sd: np.ndarray, targets, until: str | None = None):
        """The parameter posteriors of the network's latent sequences.

        Parameters
        ----------
        mu, sd : ndarray, shape (..., T, K)
            The network's latent means and stds after every frame.
        targets : sequence of str
            The network's supervised dimensions (``config.targets``).
        until : str, optional
            Stop before this stage (what its fit reads).

        Returns
        -------
        mu, sd : ndarray, shape (..., T, 4)
            Normalised, ``PARAMS`` order, after every stage.
        track : ndarray, shape (..., T, 2)
            The network's track, metres.
        """
        pos = positions(mu, targets)
        idx = param_index(targets)
        m, s = mu[..., idx], sd[..., idx]
        for stage in self.stages:
            if stage.name == until:
                break
            m, s = stage.apply(m, s, pos)
        return m, s, pos

    def start(self, batch: int = 1) -> list:
        """Streaming states of every stage, ``batch`` videos."""
        return [s.start(batch) for s in self.stages]

    def step(self, carries: list, mu: np.ndarray, sd: np.ndarray, pos: np.ndarray):
        """One frame: ``mu``, ``sd`` (B, 4) normalised ``PARAMS`` posterior of the network,
        ``pos`` (B, 2) its position (m); returns them after every stage."""
        for stage, carry in zip(self.stages, carries):
            mu, sd = stage.step(carry, mu, sd, pos)
        return mu, sd

    def describe(self, config=None) -> str:
        """``network (...) -> stage (summary) -> ...`` in one line; with the network's
        ``config``, its frame size and rolling statistic (part of the network, not a stage)."""
        net = "network"
        if config is not None:
            h, w = config.frame_size
            roll = f"rolling statistic {config.roll_stat!r}" if config.roll_features else \
                "no rolling statistic"
            net = f"network ({h}x{w}, {roll})"
        return " -> ".join([net] + [f"{s.name} {s.summary()}".strip() for s in self.stages])


def legacy_stages(ck: dict, net) -> list[dict]:
    """``checkpoint["stages"]`` of a checkpoint of the older format (``LEGACY_KEYS``)."""
    out = []
    for key in LEGACY_KEYS:
        rec = ck.get(key)
        if not rec:
            continue
        cls = next(c for c in STAGES.values() if c.legacy_key == key)
        if cls is PriorNoise:
            weights = None if net.phys_prior is None else {
                k: v.detach().clone() for k, v in net.phys_prior.state_dict().items()}
            out.append({"name": cls.name, "state": {"record": rec, "weights": weights}})
        else:
            out.append({"name": cls.name, "state": rec})
    return out


def describe(ck: dict, source, net) -> str:
    """One line: the checkpoint's network and its stages in order."""
    fmt = "stages" if "stages" in ck else "older format, converted on load"
    return f"{Pipeline.from_checkpoint(ck, source, net).describe(net.config)} [{fmt}]"


def calibrate(net, ds, lengths=(50, 100, 150, 200), batch: int = 100,
              level: float = 0.9) -> np.ndarray:
    """Per-dimension factors for the network's stds so that ``level`` intervals hold ``level``
    of the truths on ``ds`` (pooled over ``lengths``): the networks come out overconfident on
    some parameters (90% intervals holding 72-80% of d's truths), a factor fixes that after
    training without touching the means. ``r`` is calibrated on the videos where the ball
    rolls (``rolls_mask``) only: elsewhere nothing in the video tells r and its interval is
    meant to stay prior-wide; pooled, those wide intervals shrank the factor (0.86) and left
    rolling videos' intervals holding 79% of the truths.

    Parameters
    ----------
    net : Vid2ParamNet
    ds : Dataset-like (frames, states, theta/labels, floor), calibration videos
    lengths : prefix lengths pooled

    Returns
    -------
    ndarray, shape (K,)
        Factors for the supervised dimensions, ``config.targets`` order.
    """
    import torch
    from scipy.stats import norm

    from methods.vid2param.data import rolls_mask, targets_from_dataset

    names = net.config.targets
    frames = np.asarray(ds.frames)
    lengths = [int(L) for L in lengths if L <= frames.shape[1]] or [frames.shape[1]]
    sel = [L - 1 for L in lengths]
    mus, sds = [], []
    with torch.no_grad():
        for i in range(0, len(frames), batch):
            mu, sd, _ = net.filter(torch.as_tensor(frames[i:i + batch]))
            mus.append(mu[:, sel, :len(names)].numpy())
            sds.append(sd[:, sel, :len(names)].numpy())
    mu, sd = np.concatenate(mus), np.concatenate(sds)
    tg = targets_from_dataset(ds, names)[:, sel]
    z = np.abs(mu - tg) / sd  # (N, L, K)
    q = np.quantile(z.reshape(-1, len(names)), level, axis=0)
    rolls = rolls_mask(ds.states, ds.floor) if "r" in names else None
    if "r" in names and rolls.any():
        i = names.index("r")
        q[i] = np.quantile(z[rolls, :, i], level)
    return (q / norm.ppf(0.5 + level / 2)).astype(np.float64)
