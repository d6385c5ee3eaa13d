"""Accuracy tables: a refinement and the baselines against a capture's ground truth."""

from __future__ import annotations

from .baselines import bicubic, guided
from .capture import Capture
from .metrics import evaluate
from .refinement import Refinement

BASELINES = {"bicubic": bicubic, "guided": guided}


def accuracy_rows(capture: Capture, refinement: Refinement, extra: dict | None = None) -> list[dict]:
    """Rows {"method", "mae_deg", "rmse_mm", "pixels"}: the baselines, ``extra`` methods, then ours.

    Requires ``capture.groundtruth``; every method is evaluated over the same pixels.
    """
    if capture.groundtruth is None:
        raise ValueError("the capture has no ground truth (groundtruth/ folder); accuracy needs a synthetic capture")
    methods = {name: fn(capture) for name, fn in BASELINES.items()}
    methods.update(extra or {})
    methods[refinement.method] = refinement
    return [{"method": name, **evaluate(result, capture.groundtruth)} for name, result in methods.items()]


def markdown_table(rows: list[dict]) -> str:
    """A markdown table of accuracy rows."""
    lines = ["| method | normal MAE (deg) | depth RMSE (mm) |", "|---|---:|---:|"]
    lines += [f"| {r['method']} | {r['mae_deg']:.2f} | {r['rmse_mm']:.3f} |" for r in rows]
    return "\n".join(lines)
