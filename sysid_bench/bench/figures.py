"""Figure output shared by the experiments: headless backend, atomic PNG writes."""

from __future__ import annotations

from pathlib import Path

import matplotlib

from sysid_bench._io import atomic_write

matplotlib.use("Agg")  # reports are rendered on machines with no display

__all__ = ["save_figure", "method_color"]


def save_figure(fig, path) -> Path:
    """Save ``fig`` as PNG at ``path`` atomically (:func:`sysid_bench._io.atomic_write`) and close it."""
    import matplotlib.pyplot as plt

    try:
        fig.tight_layout()
        # "tight": legends placed outside the axes (off the data) stay in the picture
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110,
                                                          bbox_inches="tight"))
    finally:
        plt.close(fig)


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
