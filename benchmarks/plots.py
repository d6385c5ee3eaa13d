"""Minimal line plots drawn with OpenCV (no matplotlib): white canvas, axes, ticks, legend."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np

COLOURS = [(200, 80, 30), (40, 40, 220), (40, 160, 40), (160, 40, 160), (0, 140, 220)]  # BGR
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    if hi <= lo:
        return [lo]
    step = 10 ** math.floor(math.log10((hi - lo) / count))
    step *= next(m for m in (1, 2, 5, 10) if (hi - lo) / (step * m) <= count)
    return [k * step for k in range(math.ceil(lo / step), math.floor(hi / step) + 1)]


def line_plot(path, series: dict, *, title: str, xlabel: str, ylabel: str, logx: bool = False,
              size: tuple[int, int] = (640, 420)) -> None:
    """Write a PNG of one or more lines: ``series`` maps a label to (xs, ys)."""
    W, H = size
    left, right, top, bottom = 70, 20, 40, 55
    img = np.full((H, W, 3), 255, np.uint8)
    fx = (lambda x: math.log10(x)) if logx else float
    xs = [fx(x) for xy in series.values() for x in xy[0]]
    ys = [float(y) for xy in series.values() for y in xy[1]]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(ys), max(ys)
    pad = 0.08 * (y1 - y0 or abs(y1) or 1.0)
    y0, y1 = y0 - pad, y1 + pad
    x1 = x1 if x1 > x0 else x0 + 1.0

    def px(x, y):
        return (int(left + (fx(x) - x0) / (x1 - x0) * (W - left - right)),
                int(H - bottom - (y - y0) / (y1 - y0) * (H - top - bottom)))

    cv2.rectangle(img, (left, top), (W - right, H - bottom), (0, 0, 0), 1)
    xticks = sorted({x for xy in series.values() for x in xy[0]}) if logx else _ticks(x0, x1)
    for x in xticks:
        p = px(x, y0)
        cv2.line(img, (p[0], H - bottom), (p[0], H - bottom + 5), (0, 0, 0), 1)
        cv2.putText(img, f"{x:g}", (p[0] - 12, H - bottom + 20), FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for y in _ticks(y0, y1):
        p = px(10 ** x0 if logx else x0, y)
        cv2.line(img, (left - 5, p[1]), (left, p[1]), (0, 0, 0), 1)
        cv2.line(img, (left + 1, p[1]), (W - right - 1, p[1]), (230, 230, 230), 1)
        cv2.putText(img, f"{y:g}", (5, p[1] + 4), FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for k, (label, (lx, ly)) in enumerate(series.items()):
        colour = COLOURS[k % len(COLOURS)]
        points = [px(x, y) for x, y in zip(lx, ly)]
        for a, b in itertools.pairwise(points):
            cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in points:
            cv2.circle(img, p, 3, colour, -1, cv2.LINE_AA)
        cv2.putText(img, label, (left + 10, top + 18 + 16 * k), FONT, 0.45, colour, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left + 90, 20), FONT, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, ((W - left) // 2, H - 12), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (5, top - 8), FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot write the plot {path}")
