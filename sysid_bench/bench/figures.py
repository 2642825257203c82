"""Figure output shared by the experiments: headless backend, atomic PNG writes."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # reports are rendered on machines with no display

__all__ = ["save_figure", "method_color"]


def save_figure(fig, path) -> Path:
    """Save ``fig`` as PNG at ``path`` atomically (temp file + ``os.replace``) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fig.tight_layout()
        fig.savefig(tmp, format="png", dpi=110)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if tmp.exists():
            tmp.unlink()
    return path


def method_color(method: str) -> str:
    """The same colour for a method in every figure: its declared ``color``, else the slot
    ``figure_order`` of tab10, else one of the two slots no shipped method takes (by name)."""
    import matplotlib

    try:
        import methods

        spec = methods.spec(method)
        color, k = spec.color, spec.figure_order
    except (ValueError, ImportError):  # a store's method that is no longer registered/installed
        color, k = None, None
    if color is not None:
        return matplotlib.colors.to_hex(color)
    if k is None:
        k = 8 + sum(map(ord, method)) % 2
    return matplotlib.colors.to_hex(matplotlib.colormaps["tab10"](k % 10))
