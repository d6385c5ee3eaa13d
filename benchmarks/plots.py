"""The benchmarks' figures, drawn with matplotlib (Agg, no display): line plots, the log-log
scaling plot with its fitted power law, error maps with a colour bar, and labelled image rows.
Every axis names its quantity and unit."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

DPI = 120


def _save(fig, path) -> None:
    """Write ``fig`` as a PNG at ``path`` and close it."""
    fig.savefig(Path(path), dpi=DPI, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)


def _plain(value: float, _position=None) -> str:
    """Tick text without exponents: 5, 20, 300, 2k, 1.5M."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def line_plot(path, series: dict, *, title: str, xlabel: str, ylabel: str, logx: bool = False,
              size: tuple[float, float] = (6.4, 4.2)) -> None:
    """Write a PNG of one or more lines with markers: ``series`` maps a label to (xs, ys).

    ``logx`` puts x on a log axis, ticked at the data's x values. ``size``: inches (width, height).
    """
    fig, ax = plt.subplots(figsize=size)
    for label, (xs, ys) in series.items():
        ax.plot(xs, ys, marker="o", label=label)
    if logx:
        ax.set_xscale("log")
        ticks = sorted({x for xs, _ in series.values() for x in xs})
        ax.set_xticks(ticks)
        ax.xaxis.set_major_formatter(FuncFormatter(_plain))
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize="small")
    _save(fig, path)


def scaling_plot(path, series: dict, fits: dict, *, title: str, xlabel: str, ylabel: str) -> None:
    """Log-log plot of measured points and fitted power laws.

    series: label -> (xs, ys) measured points (both > 0). fits: label -> (exponent, prefactor)
    of ``y = prefactor * x**exponent``, drawn as a dashed line over that series' x range and
    named in the legend.
    """
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for k, (label, (xs, ys)) in enumerate(series.items()):
        colour = f"C{k}"
        ax.plot(xs, ys, "o", color=colour, label=f"{label} (measured)")
        if label in fits:
            exponent, prefactor = fits[label]
            x = np.geomspace(min(xs), max(xs), 50)
            ax.plot(x, prefactor * x ** exponent, "--", color=colour,
                    label=f"{label}: fit $\\propto$ work$^{{{exponent:.2f}}}$")
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(_plain))
        axis.set_minor_formatter(NullFormatter())
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize="small")
    _save(fig, path)


def error_maps(path, maps: dict, *, vmax: float, title: str, unit: str = "deg", scale_px: float | None = None) -> None:
    """Error maps side by side on one colour scale (0 to ``vmax``, larger values at the top
    colour) with a colour bar; NaN pixels (not evaluated) are white.

    maps: label -> (H, W) array, all the same size. ``scale_px``: colour pixels per axis tick
    step, None for plain pixel ticks.
    """
    n = len(maps)
    first = next(iter(maps.values()))
    height, width = first.shape
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n + 0.8, 3.2 * height / width + 0.6), squeeze=False,
                             layout="constrained")
    cmap = plt.get_cmap("inferno").with_extremes(bad="white")
    image = None
    for ax, (label, error) in zip(axes[0], maps.items()):
        image = ax.imshow(np.ma.masked_invalid(error), cmap=cmap, vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_title(label, fontsize="medium")
        ax.set_xlabel("column (px)")
    axes[0][0].set_ylabel("row (px)")
    for ax in axes[0][1:]:
        ax.tick_params(labelleft=False)
    fig.colorbar(image, ax=axes[0].tolist(), label=f"normal error ({unit})", extend="max", shrink=0.9)
    fig.suptitle(title)
    _save(fig, path)


def image_row(path, images: list, titles: list[str], *, title: str | None = None, width: float = 3.2) -> None:
    """RGB images (H, W, 3) uint8 or floats in [0, 1] side by side, each titled, without axes."""
    n = len(images)
    height, w = np.shape(images[0])[:2]
    fig, axes = plt.subplots(1, n, figsize=(width * n, width * height / w + (0.7 if title else 0.4)), squeeze=False,
                             layout="constrained")
    for ax, image, label in zip(axes[0], images, titles):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(label, fontsize="medium")
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    _save(fig, path)
