"""The checks of an :class:`~sysid_bench.core.estimator.Observation`'s fields that the systems' own
``check_observation`` hooks use (:mod:`sysid_bench.core.systems`): below both the estimator and the
systems, so that neither imports the other back (the estimator re-exports the constants). The
check against the scenes' reach is :func:`sysid_bench.core.systems._scene.check_within`, next to it.
"""

from __future__ import annotations

import numpy as np

from sysid_bench.core._validate import check_number
from sysid_bench.core.physics import BOX_WIDTH

__all__ = ["DT_RANGE", "BOX_MARGIN", "check_dt", "check_in_box", "check_in_view"]

#: Accepted seconds between frames: 10 kHz high-speed cameras to one frame a second. Outside it
#: the simulator's event location and the trackers' finite differences lose their meaning.
DT_RANGE = (1e-4, 1.0)
#: How far (m) positions and ``state0`` may lie outside the box. Tracking puts a ball that touches
#: a wall a few mm outside (RMS error 0.006-0.009 m on clean 28x28 video), and the noisy-position
#: studies add noise of a few cm; 0.25 m is well beyond both and far below any real mistake (a
#: wrong unit, a wrong axis). Positions within the margin are moved onto the box's edge.
BOX_MARGIN = 0.25


def check_in_box(pos: np.ndarray, floor: float | None, name: str) -> None:
    """Positions (N, 2) (NaN = unseen) within :data:`BOX_MARGIN` of the box; ``ValueError`` if not.

    With an unknown floor only x and the height of the y extent can be checked.
    """
    seen = np.isfinite(pos).all(axis=1)
    if not seen.any():
        return
    x, y = pos[seen, 0], pos[seen, 1]
    m = BOX_MARGIN
    what = f"{name}: expected positions within {m:g} m of the box"
    if x.min() < -m or x.max() > BOX_WIDTH + m:
        raise ValueError(f"{what}: x in [0, {BOX_WIDTH:g}] m, got x in [{x.min():.4g}, {x.max():.4g}]")
    if floor is not None:
        if y.min() < floor - m or y.max() > floor + BOX_WIDTH + m:
            raise ValueError(
                f"{what}: y in [{floor:g}, {floor + BOX_WIDTH:g}] m (floor {floor:g}), "
                f"got y in [{y.min():.4g}, {y.max():.4g}]"
            )
    elif y.max() - y.min() > BOX_WIDTH + 2 * m:
        raise ValueError(
            f"{what}: y spanning at most {BOX_WIDTH:g} m, got y in [{y.min():.4g}, {y.max():.4g}]"
        )


def check_in_view(pos: np.ndarray, system, name: str) -> None:
    """Points (N, 2) (NaN = unseen) near a system's view; ``ValueError`` if far outside it.

    The margin is half the view's larger side: a point drawn at the edge of the view, noise and
    tracking error all pass; a wrong unit (millimetres for metres) or a wrong axis does not.
    """
    seen = np.isfinite(pos).all(axis=1)
    if not seen.any():
        return
    x0, x1, y0, y1 = (float(v) for v in system.extent)
    m = max(BOX_MARGIN, 0.5 * max(x1 - x0, y1 - y0))
    x, y = pos[seen, 0], pos[seen, 1]
    if x.min() < x0 - m or x.max() > x1 + m or y.min() < y0 - m or y.max() > y1 + m:
        raise ValueError(
            f"{name}: expected points within {m:g} m of the {system.name} system's view "
            f"x in [{x0:g}, {x1:g}], y in [{y0:g}, {y1:g}] m, got x in [{x.min():.4g}, "
            f"{x.max():.4g}], y in [{y.min():.4g}, {y.max():.4g}]"
        )



def check_dt(dt) -> float:
    """Seconds between frames in :data:`DT_RANGE`, as a float; ``ValueError`` naming ``dt``."""
    return check_number(dt, "dt", lo=DT_RANGE[0], hi=DT_RANGE[1], unit="s")
