"""Figure output shared by the experiments: headless backend, atomic PNG writes."""

from __future__ import annotations

import functools
from pathlib import Path

import matplotlib

from sysid_bench.core._io import atomic_write

matplotlib.use("Agg")  # reports are rendered on machines with no display

__all__ = ["save_figure", "method_color", "method_style", "method_claims"]


def save_figure(fig, path) -> Path:
    """Save ``fig`` as PNG at ``path`` atomically (:func:`sysid_bench.core._io.atomic_write`) and close it."""
    import matplotlib.pyplot as plt

    try:
        fig.tight_layout()
        # "tight": legends placed outside the axes (off the data) stay in the picture
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110,
                                                          bbox_inches="tight"))
    finally:
        plt.close(fig)


@functools.lru_cache(maxsize=1)
def _style() -> dict:
    """``style.toml`` beside this module: ``{method: {"order": int, "claims": str}}``."""
    import tomllib

    with open(Path(__file__).with_name("style.toml"), "rb") as f:
        return tomllib.load(f).get("methods", {})


def method_style(method: str) -> dict:
    """How the report draws and names ``method`` (``order``, ``claims``; empty when the style
    file does not list it)."""
    return dict(_style().get(method, {}))


def method_claims(method: str) -> str:
    """The few words the readings use for ``method`` (its ``claims`` in the style file), else
    its name."""
    return method_style(method).get("claims", method)


def method_color(method: str) -> str:
    """The same colour for a method in every figure: the slot ``order`` of tab10 that the style
    file gives it, else one of the two slots no listed method takes (by name)."""
    import matplotlib

    k = method_style(method).get("order")
    if k is None:
        k = 8 + sum(map(ord, method)) % 2
    return matplotlib.colors.to_hex(matplotlib.colormaps["tab10"](int(k) % 10))
