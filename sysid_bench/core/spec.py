"""What a method declares about itself, read by the harness instead of tables keyed by name.

A method's class sets plain class attributes (defaults on :class:`~sysid_bench.core.estimator.Estimator`,
so a minimal class sets only ``name`` and ``input_kind``); :meth:`Estimator.spec` collects them,
checks them once and returns a frozen :class:`MethodSpec`, the one record the runner, the scales,
the figures, calibration, sensitivity, the report and :func:`sysid_bench.core.testing.check_estimator`
read. The idea is Gymnasium's ``EnvSpec`` (a small frozen record of how to make and run a thing),
kept on the class so that the one file of a method holds everything about it.

Declarations
------------
Two kinds, kept apart as scikit-learn keeps its estimator tags apart from the benchmark's
settings: what a method *is* (:class:`Traits`, ``spec.traits``: what it takes and
what it can answer, checked by :func:`sysid_bench.core.testing.check_estimator`) and how the
benchmark *schedules* it (:class:`Schedule`, ``spec.schedule``: caps, options per scale,
threads, colour, order). ``spec.<field>`` reads either (the flat names the harness reads).

What a method is (:class:`Traits`):

=====================  ==========  =====================================================================
attribute              default     meaning
=====================  ==========  =====================================================================
``input_kind``         positions   ``"positions"`` (tracked or given) or ``"frames"`` (pixels)
``min_frames``         1           fewest frames ``identify`` accepts
``identifies``         True        ``identify`` returns a Posterior (else raises NotImplementedError)
``forecasts``          False       ``forecast`` returns a Forecast (else raises NotImplementedError)
``streams``            False       ``identify_prefixes`` does one pass over all prefixes
``online``             False       ``stream()`` is recurrent: a ``push`` costs the same at every frame
                                   (not the re-identifying ``LoopStream``); the stream tells its
                                   position now and, if the method forecasts, forecasts itself
``trains``             False       ``fit`` learns from a training set (sensitivity experiment)
``reference_posterior`` False      the posterior calibration compares every other method with
``systems``            ("ball",)  the systems it runs on: a tuple of registered names, or ``"any"``
                                   (every registered system, one a user registers included); one
                                   class answers on each (``methods.get(name, system=S)``) and
                                   ``check_estimator`` checks it on each
=====================  ==========  =====================================================================

How the benchmark schedules it (:class:`Schedule`):

=====================  ==========  =====================================================================
attribute              default     meaning
=====================  ==========  =====================================================================
``cost``               10          relative cost of one cell: the runner starts costly cells first;
                                   ``>= EXPENSIVE_COST`` is the expensive tier (fewer frame counts)
``scale_cases``        {}          per scale: most test videos (an int, or a dict per experiment)
``scale_options``      {}          per scale: hyperparameters the benchmark passes to ``methods.get``
``fit_options``        {}          per scale: hyperparameters of the sensitivity experiment's training
``pretrained``         {}          per scale: ``{condition: hyperparameters}`` of ready-trained
                                   sensitivity models, loaded instead of training one
                                   (``"<system>/<condition>"``: one system's)
``threads_param``      None        the hyperparameter setting the method's own thread count, if any
``inline``             False       cells run in a thread of the runner's process (cheap, heavy import)
``online_cost``        False       a row of the online-cost table by default (report section 7)
``policies``           {}          interception policies built on the method's online stream:
                                   ``{policy name: hyperparameters}`` (``sysid-bench intercept``)
``from_paper``         False       the paper's claims are about this method (the readings compare
                                   these with the baselines); how the report names, draws and orders
                                   a method is the report's (``sysid_bench/bench/style.toml``)
``paper_baseline``     False       the paper compared its method with this one given true positions
                                   and initial state (the readings check that claim against it)
``contract_options``   {}          cheap hyperparameters for ``check_estimator`` (same code path)
=====================  ==========  =====================================================================

``name`` (required) is the registry name.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = ["MethodSpec", "Traits", "Schedule", "EXPENSIVE_COST", "INPUT_KINDS",
           "CAPABILITIES", "spec_of"]

#: Cells of a method with at least this ``cost`` are the expensive tier: in scales that thin
#: them (smoke, default) they are evaluated at fewer frame counts (see ``Scale``).
EXPENSIVE_COST = 20
INPUT_KINDS = ("positions", "frames")
#: the yes/no capabilities (``spec.capabilities`` lists those a method has)
CAPABILITIES = ("identifies", "forecasts", "streams", "online", "trains")
#: what a method is
TRAIT_FIELDS = ("input_kind", "min_frames", *CAPABILITIES, "reference_posterior", "systems")
#: how the benchmark schedules it
SCHEDULE_FIELDS = (
    "cost", "scale_cases", "scale_options", "fit_options", "pretrained", "threads_param",
    "inline", "online_cost", "policies", "from_paper", "paper_baseline", "contract_options",
)
#: class attributes collected into a MethodSpec
DECLARED = ("name", *TRAIT_FIELDS, *SCHEDULE_FIELDS)


def _frozen(d) -> Mapping:
    return MappingProxyType({k: _frozen(v) if isinstance(v, Mapping) else v for k, v in d.items()})


def _plain(x):
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


@dataclass(frozen=True)
class Traits:
    """What a method is: the input it takes and what it can answer (see the module docstring).

    No defaults here: they are the class attributes of ``sysid_bench.core.estimator.Estimator``,
    the one place a method's declarations start from (:func:`spec_of` reads every field from
    the class).
    """

    input_kind: str
    min_frames: int
    identifies: bool
    forecasts: bool
    streams: bool
    online: bool
    trains: bool
    reference_posterior: bool
    #: registered system names, or ``"any"``
    systems: tuple | str


@dataclass(frozen=True, eq=False)
class Schedule:
    """How the benchmark runs a method (see the module docstring); no defaults here either."""

    cost: int
    scale_cases: Mapping
    scale_options: Mapping
    fit_options: Mapping
    pretrained: Mapping
    threads_param: str | None
    inline: bool
    online_cost: bool
    policies: Mapping
    from_paper: bool
    paper_baseline: bool
    contract_options: Mapping


@dataclass(frozen=True, eq=False)
class MethodSpec:
    """A method's declarations, checked: its name, what it is (``traits``) and how the
    benchmark schedules it (``schedule``).

    Built by :func:`spec_of` from the class; ``entry_point`` is filled in by the registry.
    Every field of either part reads as ``spec.<field>`` too (``spec.forecasts``,
    ``spec.cost``).
    """

    name: str
    traits: Traits
    schedule: Schedule
    entry_point: str | None = None
    #: the declarations' defaults (those of the base class that first declares each), which
    #: ``repr`` leaves out; not part of the record
    _defaults: Mapping = field(default_factory=lambda: MappingProxyType({}), repr=False,
                               compare=False)

    def __getattr__(self, attr: str):
        # only called for names that are not attributes of the record itself
        if attr in TRAIT_FIELDS:
            return getattr(self.traits, attr)
        if attr in SCHEDULE_FIELDS:
            return getattr(self.schedule, attr)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {attr!r}")

    @property
    def capabilities(self) -> tuple[str, ...]:
        """The declared yes/no capabilities, e.g. ``("identifies", "forecasts")`` (the full
        record of what the method is: ``traits``)."""
        return tuple(c for c in CAPABILITIES if getattr(self.traits, c))

    def runs_on(self, system: str) -> bool:
        """Whether the method declares ``system`` (a registered name) among its systems."""
        return self.systems == "any" or system in self.systems

    @property
    def expensive(self) -> bool:
        """The expensive tier (``cost >= EXPENSIVE_COST``)."""
        return self.cost >= EXPENSIVE_COST

    def cases_cap(self, scale: str, experiment: str) -> int | None:
        """Most test videos of ``experiment`` at ``scale`` (None: no cap)."""
        cap = self.scale_cases.get(scale)
        if isinstance(cap, Mapping):
            cap = cap.get(experiment)
        return None if cap is None else int(cap)

    def options(self, scale: str, threads: int | None = 1) -> dict:
        """Hyperparameters the benchmark passes at ``scale`` (``threads`` into ``threads_param``)."""
        out = {}
        if self.threads_param is not None and threads is not None:
            out[self.threads_param] = int(threads)
        out.update(_plain(self.scale_options.get(scale, {})))
        return out

    def training_options(self, scale: str) -> dict:
        """Hyperparameters of the sensitivity experiment's training at ``scale``."""
        return _plain(self.fit_options.get(scale, {}))

    def pretrained_options(self, scale: str, condition: str,
                           system: str = "ball") -> dict | None:
        """Hyperparameters that load the ready-trained model of a sensitivity ``condition`` of
        ``system`` at ``scale`` (e.g. ``{"checkpoint": ...}``), or None: train one. A key
        ``"<system>/<condition>"`` is that system's model; a bare ``"<condition>"`` serves
        every system."""
        per = self.pretrained.get(scale, {})
        got = per.get(f"{system}/{condition}", per.get(condition))
        return None if got is None else _plain(got)

    def as_dict(self) -> dict:
        """Plain, JSON-ready flat copy, every declaration by name (part of the method's
        fingerprint in a results store)."""
        return _plain({"name": self.name, **{a: getattr(self, a) for a in DECLARED[1:]},
                       "entry_point": self.entry_point})

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), sort_keys=True, default=str)

    def __eq__(self, other) -> bool:
        return isinstance(other, MethodSpec) and self.as_dict() == other.as_dict()

    __hash__ = None  # holds mappings

    def __repr__(self) -> str:
        d = self.as_dict()
        diff = {k: v for k, v in d.items() if k == "name" or self._defaults.get(k) != v}
        return "MethodSpec(" + ", ".join(f"{k}={v!r}" for k, v in diff.items()) + ")"


def _bad(cls, attr: str, expected: str, got) -> ValueError:
    return ValueError(f"{cls.__name__}.{attr}: expected {expected}, got {got!r}")


def _check_per_scale(cls, attr: str, value, params, *, cases: bool = False) -> Mapping:
    if not isinstance(value, Mapping):
        raise _bad(cls, attr, "a dict keyed by scale name", value)
    for scale, v in value.items():
        if not isinstance(scale, str):
            raise _bad(cls, attr, "scale names (str) as keys", scale)
        if cases:
            vals = v.values() if isinstance(v, Mapping) else [v]
            for n in vals:
                if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                    raise _bad(cls, f"{attr}[{scale!r}]", "an int >= 0 or a dict of them", v)
        else:
            if not isinstance(v, Mapping):
                raise _bad(cls, f"{attr}[{scale!r}]", "a dict of hyperparameters", v)
            unknown = sorted(set(v) - set(params)) if params is not None else []
            if unknown:
                raise _bad(cls, f"{attr}[{scale!r}]", f"hyperparameters among {params}", unknown)
    return _frozen(value)


def spec_of(cls, entry_point: str | None = None) -> MethodSpec:
    """Collect and check the declarations of an Estimator subclass.

    Raises
    ------
    ValueError
        A declaration of the wrong type, an unknown input kind, or options naming
        hyperparameters the constructor does not take; the message names ``Class.attribute``.
    """
    params = cls._param_names()
    vals = {a: getattr(cls, a) for a in DECLARED}
    name = vals["name"]
    if not isinstance(name, str) or not name or name == "estimator":
        raise _bad(cls, "name", "the method's registry name (a non-empty str)", name)
    if vals["input_kind"] not in INPUT_KINDS:
        raise _bad(cls, "input_kind", f"one of {INPUT_KINDS}", vals["input_kind"])
    for a in (*CAPABILITIES, "inline", "online_cost", "reference_posterior", "from_paper",
              "paper_baseline"):
        if not isinstance(vals[a], bool):
            raise _bad(cls, a, "True or False", vals[a])
    sy = vals["systems"]
    if sy != "any":
        if (not isinstance(sy, (tuple, list)) or not sy
                or not all(isinstance(x, str) and x for x in sy) or len(set(sy)) != len(sy)):
            raise _bad(cls, "systems", '"any" or a non-empty tuple of distinct system names', sy)
        vals["systems"] = tuple(sy)
    for a in ("min_frames", "cost"):
        v = vals[a]
        if isinstance(v, bool) or not isinstance(v, int) or v < (1 if a == "min_frames" else 0):
            raise _bad(cls, a, "an int >= " + ("1" if a == "min_frames" else "0"), v)
    tp = vals["threads_param"]
    if tp is not None and tp not in params:
        raise _bad(cls, "threads_param", f"None or one of the hyperparameters {params}", tp)
    vals["scale_cases"] = _check_per_scale(cls, "scale_cases", vals["scale_cases"], None, cases=True)
    vals["scale_options"] = _check_per_scale(cls, "scale_options", vals["scale_options"], params)
    vals["fit_options"] = _check_per_scale(cls, "fit_options", vals["fit_options"], params)
    pre = vals["pretrained"]
    if not isinstance(pre, Mapping):
        raise _bad(cls, "pretrained", "a dict keyed by scale name", pre)
    for scale, conds in pre.items():
        if not isinstance(scale, str) or not isinstance(conds, Mapping):
            raise _bad(cls, "pretrained", "{scale: {condition: hyperparameters}}", pre)
        _check_per_scale(cls, f"pretrained[{scale!r}]", conds, params)
    vals["pretrained"] = _frozen(pre)
    co = vals["contract_options"]
    if not isinstance(co, Mapping) or set(co) - set(params):
        raise _bad(cls, "contract_options", f"a dict of hyperparameters among {params}", co)
    vals["contract_options"] = _frozen(co)
    pol = vals["policies"]
    if not isinstance(pol, Mapping) or not all(isinstance(k, str) and k for k in pol):
        raise _bad(cls, "policies", "a dict {policy name: hyperparameters}", pol)
    for k, v in pol.items():
        if not isinstance(v, Mapping) or set(v) - set(params):
            raise _bad(cls, f"policies[{k!r}]", f"a dict of hyperparameters among {params}", v)
    if pol and not (vals["online"] and vals["forecasts"]):
        raise _bad(cls, "policies", "{} for a method that is not online or does not forecast "
                   "(a policy forecasts from the method's stream)", pol)
    vals["policies"] = _frozen(pol)
    return MethodSpec(
        name=name,
        traits=Traits(**{a: vals[a] for a in TRAIT_FIELDS}),
        schedule=Schedule(**{a: vals[a] for a in SCHEDULE_FIELDS}),
        entry_point=entry_point,
        _defaults=_frozen(_base_defaults(cls)),
    )


def _base_defaults(cls) -> dict:
    """Each declaration's value on the most basic class of ``cls`` that sets it (the
    ``Estimator`` base: the defaults), read from the class itself so that this module needs
    no import of the estimator module (which imports this one)."""
    out = {}
    for a in DECLARED:
        for klass in reversed(cls.__mro__):
            if a in vars(klass):
                out[a] = _plain(vars(klass)[a])
                break
    return out
