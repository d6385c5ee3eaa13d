"""summary.md and the PNG plots, rebuilt from whichever result files exist in a folder
(``python -m benchmarks summary`` does only this: no benchmark runs)."""

from __future__ import annotations

import json
from pathlib import Path

from . import room, scaling
from .accuracy import markdown as accuracy_table
from .plots import line_plot


def _load(out: Path, name: str) -> list[dict]:
    path = out / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else []


def _study_table(rows: list[dict]) -> str:
    lines = ["| mesh | SF | protocol | frames | tau~ | MAE (deg) | RMSE (mm) | seconds |",
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['mesh']} | {r['sf']} | {r.get('protocol', 'dense')} | {r['frames']} | {r['tau']:g} | "
              f"{r['mae_deg']:.2f} | {r['rmse_mm']:.3f} | {r['seconds']:.1f} |" for r in rows]
    return "\n".join(lines)


def _speed_table(rows: list[dict]) -> str:
    stages = sorted({k for r in rows for k in r["breakdown"] if k != "total"})
    lines = ["| colour | depth | object pixels | frames | seconds | CPU seconds | peak MB | finest CG per step (max) | "
             + " | ".join(stages) + " |",
             "|---|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(stages)]
    for r in rows:
        parts = " | ".join(f"{r['breakdown'].get(k, 0.0):.1f}" for k in stages)
        cg = [c for c in r.get("finest_cg_iterations") or [] if c is not None]
        lines.append(f"| {r['color']} | {r['depth']} | {r.get('object_pixels', '')} | {r['frames']} | "
                     f"{r['seconds']:.1f} | {r['cpu_seconds']:.1f} | {r['peak_mb']:.0f} | {max(cg, default='')} | "
                     f"{parts} |")
    return "\n".join(lines)


def _study_plots(out: Path, rows: list[dict], study: str, key: str, xlabel: str, logx: bool) -> list[str]:
    names = []
    protocols = dict.fromkeys(r.get("protocol", "dense") for r in rows)
    for metric, metric_label in (("mae_deg", "normal MAE (deg)"), ("rmse_mm", "depth RMSE (mm)")):
        name = f"{study}_{metric.split('_')[0]}.png"
        series = {}
        for protocol in protocols:
            mine = [r for r in rows if r.get("protocol", "dense") == protocol]
            series_label = f"{mine[0]['mesh']} SF {mine[0]['sf']}" + (f" {protocol}" if len(protocols) > 1 else "")
            series[series_label] = ([r[key] for r in mine], [r[metric] for r in mine])
        line_plot(out / name, series, title=f"{metric_label} against {xlabel.split(' (')[0]}", xlabel=xlabel,
                  ylabel=metric_label, logx=logx)
        names.append(name)
    return names


def write_summary(out) -> Path:
    """Write ``summary.md`` (all tables) and the plots into ``out``; returns the summary's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    parts = ["# Benchmark results", ""]
    accuracy = _load(out, "accuracy")
    if accuracy:
        parts += ["## Accuracy (all methods)", "", accuracy_table(accuracy), ""]
        for mesh in dict.fromkeys(r["mesh"] for r in accuracy):
            mine = [r for r in accuracy if r["mesh"] == mesh]
            methods = dict.fromkeys(r["method"] for r in mine)
            series = {m: ([r["sf"] for r in mine if r["method"] == m], [r["mae_deg"] for r in mine if r["method"] == m])
                      for m in methods}
            if len({r["sf"] for r in mine}) > 1:
                name = f"accuracy_{mesh}_mae.png"
                line_plot(out / name, series, title=f"{mesh}: normal error against the scale factor",
                          xlabel="scale factor SF (colour pixels per depth pixel, per axis)", ylabel="normal MAE (deg)",
                          logx=True)
                parts += [f"![{mesh}]({name})", ""]
    for study, key, xlabel, logx in (("frames", "frames", "frames n (count)", False),
                                       ("tau", "tau", "tau~ (depth prior weight, dimensionless)", True)):
        rows = _load(out, study)
        if rows:
            parts += [f"## Error against {xlabel.split(' (')[0]} (ours)", "", _study_table(rows), ""]
            if len(rows) > 1:
                parts += [f"![{name}]({name})" for name in _study_plots(out, rows, study, key, xlabel, logx)] + [""]
    speed = _load(out, "speed")
    if speed:
        parts += ["## Speed and peak memory (odometry + refine, fresh process per case)", "", _speed_table(speed), ""]
    scaling_rows = _load(out, "scaling")
    if scaling_rows:
        scaling.draw_plot(out, scaling_rows)
    room.draw_pictures(out)
    path = out / "summary.md"
    path.write_text("\n".join(parts))
    return path
