"""A system's known geometry, as data: the :class:`Scene` base and one frozen dataclass per system.

A scene holds what a camera's user knows of the world the motion happens in -- the ball's floor
and walls, the pendulum's pivot, the spring's anchor, the collision track's ends and the pucks'
half-sizes -- in metres, with the design's values as defaults, so ``Scene()`` is today's world and
every simulated figure is unchanged. ``System.simulate(..., scene=)`` and ``System.observe(...,
scene=)`` honour it; ``Observation.scene`` carries it (None = the system's default).

Fields are numbers or tuples of numbers (converted to float on construction); a field declared
``optional`` in its metadata may be ``None`` (absent: a ball scene without walls). Every value
must be finite and within :data:`COORD_MAX` metres of the origin (centimetres to tens of metres,
with room to spare), so a scene that cannot be right fails where it is made, naming the field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

__all__ = ["Scene", "BallScene", "PendulumScene", "SpringScene", "CollisionScene", "COORD_MAX",
           "check_within"]

#: Largest coordinate or size a scene may hold, m (the ball's ``physics.FLOOR_MAX``): keeps
#: ~1e-13 m resolution for the kernels' float64 positions.
COORD_MAX = 1000.0


def _number(value, where: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{where}: expected a number of metres, got {type(value).__name__} {value!r}")
    v = float(value)
    if not math.isfinite(v) or abs(v) > COORD_MAX:
        raise ValueError(f"{where}: expected a finite number of metres within +-{COORD_MAX:g}, got {value!r}")
    return v


@dataclass(frozen=True)
class Scene:
    """Base of the systems' scenes: a frozen dataclass of metres, checked on construction.

    A system with no geometry of its own (a user's, say) has this empty scene. Subclasses declare
    fields (a number or a tuple of numbers; ``field(metadata={"optional": True})`` allows
    ``None``) and may add checks in :meth:`_check`.
    """

    system: ClassVar[str] = ""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            where = f"scene.{f.name}"
            if value is None:
                if not f.metadata.get("optional", False):
                    raise ValueError(f"{where}: expected a value for the {self.system or 'system'}'s "
                                     f"scene, got None (only optional fields may be None)")
                continue
            default = f.default
            if isinstance(default, tuple) or isinstance(value, (tuple, list, np.ndarray)):
                n = len(default) if isinstance(default, tuple) else None
                try:
                    items = tuple(value)
                except TypeError:
                    raise ValueError(f"{where}: expected {n or 'a tuple of'} numbers, got {value!r}") from None
                if n is not None and len(items) != n:
                    raise ValueError(f"{where}: expected {n} numbers, got {len(items)} ({value!r})")
                conv = tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(items))
            else:
                conv = _number(value, where)
            object.__setattr__(self, f.name, conv)
        self._check()

    def _check(self) -> None:
        """Checks across fields; raise ``ValueError`` naming the field."""
        return None

    def replace(self, **overrides) -> Scene:
        """A copy with ``overrides`` (field names of this scene), checked as a new one."""
        names = {f.name for f in dataclasses.fields(self)}
        for k in overrides:
            if k not in names:
                raise ValueError(f"scene: the {self.system or 'system'}'s scene has no field {k!r}; "
                                 f"its fields are {sorted(names)}")
        return dataclasses.replace(self, **overrides)

    def values(self) -> np.ndarray:
        """Every number of the scene, flat (for finiteness checks and hashing)."""
        out: list[float] = []
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            out.extend(v if isinstance(v, tuple) else (v,))
        return np.asarray(out, dtype=np.float64)


def _ordered(pair, where: str, what: str) -> None:
    if not pair[0] < pair[1]:
        raise ValueError(f"{where}: expected {what} with the first < the second, got {pair}")


@dataclass(frozen=True)
class BallScene(Scene):
    """The ball's world: a floor at height ``floor`` (m) and walls at ``walls = (left, right)``.

    Either may be ``None``: a floor alone (no walls in view: free in x), or neither (free fall).
    Defaults: the design's 10 m box, floor 0, walls at 0 and 10.
    """

    system: ClassVar[str] = "ball"
    floor: float | None = field(default=0.0, metadata={"optional": True})
    walls: tuple[float, float] | None = field(default=(0.0, 10.0), metadata={"optional": True})

    def _check(self):
        if self.walls is not None:
            _ordered(self.walls, "scene.walls", "(left, right) in metres")


@dataclass(frozen=True)
class PendulumScene(Scene):
    """The pendulum's world: the pivot at ``pivot = (x, y)`` (m). Default (0, 0)."""

    system: ClassVar[str] = "pendulum"
    pivot: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class SpringScene(Scene):
    """The spring's world: its anchor (the wall it is tied to) at ``anchor = (x, y)`` (m); the
    block moves along ``y = anchor[1]`` and ``L0`` is measured from ``anchor[0]``. Default (0, 0)."""

    system: ClassVar[str] = "spring"
    anchor: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class CollisionScene(Scene):
    """The collision's world: the track's walls at ``ends = (left, right)`` (m) and the pucks'
    half-sizes ``half_sizes = (r1, r2)`` (m, puck 1 then puck 2); the track runs along ``y = 0``
    and each tracked point is a puck's centre, ``r`` above it. Defaults: (0, 10) and (0.25, 0.25).
    """

    system: ClassVar[str] = "collision"
    ends: tuple[float, float] = (0.0, 10.0)
    half_sizes: tuple[float, float] = (0.25, 0.25)

    def _check(self):
        _ordered(self.ends, "scene.ends", "(left, right) in metres")
        if min(self.half_sizes) <= 0:
            raise ValueError(f"scene.half_sizes: expected sizes > 0 m, got {self.half_sizes}")
        room = self.ends[1] - self.ends[0]
        if 2.0 * (self.half_sizes[0] + self.half_sizes[1]) > room:
            raise ValueError(
                f"scene.half_sizes: expected both pucks to fit the track {self.ends} side by side "
                f"with room to move, got half-sizes {self.half_sizes}"
            )


def check_within(pos: np.ndarray, name: str) -> None:
    """Points (N, 2) (NaN = unseen) within the scenes' :data:`COORD_MAX` of the origin (a scene
    moves the world: only a wrong unit can still be caught); ``ValueError`` naming ``name``."""
    seen = pos[np.isfinite(pos).all(axis=1)]
    if seen.size and np.abs(seen).max() > COORD_MAX:
        raise ValueError(f"{name}: expected points within {COORD_MAX:g} m of the scene's origin, "
                         f"got up to {np.abs(seen).max():.4g} m")
