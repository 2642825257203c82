"""Policy names -> policies: the built-ins and those the registered methods declare."""

from __future__ import annotations

from sysid_bench.bench.intercept.kalman import Kalman
from sysid_bench.bench.intercept.policies import (
    Identify,
    Oracle,
    Policy,
    RandomTargets,
    React,
    StreamPolicy,
)

#: Built-in policy names -> factories (registered identifying methods are added by name).
POLICIES = {
    "oracle": lambda **o: Oracle(**o),
    "random-1hz": lambda **o: RandomTargets(1.0, **o),
    "random-2hz": lambda **o: RandomTargets(2.0, **o),
    "react": lambda **o: React(**o),
    "kalman": lambda **o: Kalman(**o),
}


def _stream_policies() -> dict[str, tuple[str, dict]]:
    """``{policy: (method, hyperparameters)}`` declared by the registered methods (``policies``:
    online methods that forecast). Reads every method's declarations (imports its module)."""
    import methods

    out: dict[str, tuple[str, dict]] = {}
    for m in methods.available():
        try:
            sp = methods.spec(m)
        except ImportError:  # a method whose packages are not installed offers no policy
            continue
        for pol, opts in sp.policies.items():
            out.setdefault(pol, (m, dict(opts)))
    return out


def _is_policy(name) -> bool:
    """A built-in policy, one declared by an online method, or a registered method that
    forecasts (its forecast sets the target)."""
    import methods

    if not isinstance(name, str):
        return False
    if name in POLICIES or name in _stream_policies():
        return True
    return name in methods.available() and methods.spec(name).forecasts


def known_policies() -> list[str]:
    """Every policy name :func:`make_policy` accepts (imports every registered method)."""
    import methods

    declared = list(_stream_policies())
    return list(POLICIES) + declared + [m for m in methods.available()
                                        if m not in POLICIES and m not in declared
                                        and _is_policy(m)]


def make_policy(name: str, **options) -> Policy:
    """A policy by name; ``options`` go to its constructor.

    Raises
    ------
    ValueError
        Unknown name (the message lists the known ones) or options the policy does not take.
    """
    if not _is_policy(name):
        known = ", ".join(known_policies())
        raise ValueError(f"policy: unknown policy {name!r}; known policies: {known}")
    try:
        if name in POLICIES:
            return POLICIES[name](**options)
        declared = _stream_policies()
        if name in declared:
            method, base = declared[name]
            return StreamPolicy(method, name=name, **{**base, **options})
        return Identify(name, **options)
    except TypeError as exc:
        raise ValueError(f"options: policy {name!r} does not take {sorted(options)} ({exc})") from exc


