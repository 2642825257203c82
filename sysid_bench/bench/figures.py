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


_ORDER = ("vid2param", "nuts", "emcee", "lsq", "bo", "sindy", "dmd", "prior")


def method_color(method: str) -> str:
    """The same colour for a method in every figure (tab10; unknown names hash into it)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    k = _ORDER.index(method) if method in _ORDER else 8 + sum(map(ord, method)) % 2
    return matplotlib.colors.to_hex(cmap(k % 10))
