"""The report of a run (``report.json``) and the summary printed at its end.

A refinement's report (:meth:`o3d_mvps.Refinement.report`) gathers, from ``Refinement.info``:
the inputs and the conventions found (``info["inputs"]``), every frame used or dropped with the
reason (``info["frames_report"]``, else built here from the frames used, the frames the
registration dropped and those the view selection left out), how far each pose moved from its
start (``info["pose_updates"]``, else computed here), the per-frame residual (RMS of the data
term at the finest level), the energy per level, time and peak memory per stage, the device and
the warnings raised. ``summary`` holds what :func:`summary_lines` prints.

Peak memory is the process's high-water mark (``ru_maxrss``, resident set) read after each stage:
cheap, and it includes NumPy's and Open3D's buffers (tracemalloc would slow the run down).
"""

from __future__ import annotations

import resource
import sys
import warnings
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from .model import se3

#: Top-level keys of a refinement's report.json, in order.
REPORT_KEYS = ("method", "energy", "energy_per_level", "timings", "info", "inputs", "frames", "poses", "light",
               "residuals", "device", "peak_memory_mb", "warnings", "summary")


#: Why a frame of the capture beyond the ``frames`` option's count was not used.
NOT_PICKED = "not picked (the frames option: --frames or RefineOptions.frames)"


def peak_memory_mb() -> float:
    """The process's peak resident memory so far, in MB (``ru_maxrss``: kB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 1024), 1)


def workers_peak_memory_mb() -> float:
    """The largest peak resident memory of the process's finished child processes (e.g. a local
    Dask cluster's workers), in MB; 0 when none has finished."""
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 1024), 1)


@contextmanager
def recorded_warnings(into: list) -> Iterator[None]:
    """Append the message of every Python warning shown inside to ``into`` (each once); the
    warnings still reach the caller's handlers (printed, or recorded by an outer
    ``catch_warnings``) as they are raised, under the caller's filters."""
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def record(message, category, filename, lineno, file=None, line=None):
            if str(message) not in into:
                into.append(str(message))
            shown(message, category, filename, lineno, file, line)

        warnings.showwarning = record
        yield


def pose_movement(initial: np.ndarray, refined: np.ndarray, frames: list) -> list[dict]:
    """How far each frame's camera moved between two pose sets (n, 4, 4), reference -> frame:
    rows {"frame", "moved_mm" (camera centre, reference coordinates), "moved_deg" (rotation)}
    (:func:`o3d_mvps.model.se3.camera_movement`)."""
    rows = []
    for f, T0, T1 in zip(frames, np.asarray(initial, dtype=np.float64), np.asarray(refined, dtype=np.float64)):
        degrees, metres = se3.camera_movement(T0, T1)
        rows.append({"frame": int(f), "moved_mm": round(metres * 1000, 4), "moved_deg": round(degrees, 5)})
    return rows


def frames_report(info: dict, files: list | None = None) -> list[dict]:
    """Every frame of the capture: rows {"index", "file", "used", "reason"} (reason None when used).

    ``info["frames_report"]`` when a reader filled it in; else from ``info["frames"]`` (used),
    ``info["dropped_frames"]`` (the registration's), ``info["views"]["left_out"]`` (the view
    selection's) and ``info["capture_frames"]`` (frames not picked by the ``frames`` option).
    ``files``: the capture's colour file names, by index, when known.
    """
    if info.get("frames_report"):
        return info["frames_report"]
    used = [int(i) for i in info.get("frames", [])]
    reasons = {int(i): why for i, why in info.get("dropped_frames", {}).items()}
    reasons.update({int(i): f"sees too little of the reference ({why})"
                    for i, why in (info.get("views") or {}).get("left_out", {}).items()})
    n = int(info.get("capture_frames", max([*used, *reasons, -1]) + 1))
    files = files if files is not None else info.get("frame_files")
    rows = []
    for i in range(n):
        reason = None if i in used else reasons.get(i, NOT_PICKED)
        rows.append({"index": i, "file": files[i] if files is not None and i < len(files) else None,
                     "used": i in used, "reason": reason})
    return rows


def energy_per_level(energy: list) -> list[dict]:
    """Rows {"level", "sweeps", "first", "last"} from the energy log, coarsest level first."""
    levels = {}
    for row in energy:
        level = levels.setdefault(row["level"], {"level": row["level"], "sweeps": 0, "first": row["energy"]})
        level["sweeps"], level["last"] = row["iteration"], row["energy"]
    return list(levels.values())


def summarise(report: dict, outputs: str | None = None) -> dict:
    """The summary of a report: frames used / dropped, the finest level's energy first -> last,
    seconds, peak memory, warnings, the input checks by status (None without checks) and the names of
    those not ok by status, the outputs."""
    frames = report.get("frames") or []
    checks = (report.get("inputs") or {}).get("checks") or []
    statuses, flagged = {}, {}
    for check in checks:
        statuses[check.get("status")] = statuses.get(check.get("status"), 0) + 1
        if check.get("status") != "ok":
            flagged.setdefault(check.get("status"), []).append(check.get("name"))
    levels = energy_per_level(report.get("energy") or [])
    finest = levels[-1] if levels else {}
    return {"frames_used": sum(r["used"] for r in frames), "frames_dropped": sum(not r["used"] for r in frames),
            "energy_first": finest.get("first"), "energy_last": finest.get("last"),
            "seconds": round(float(report.get("timings", {}).get("total", 0.0)), 2),
            "peak_memory_mb": report.get("peak_memory_mb"), "warnings": len(report.get("warnings") or []),
            "input_checks": statuses or None, "input_checks_flagged": flagged or None, "outputs": outputs}


def summary_lines(summary: dict, *, one_line: bool = False) -> list[str]:
    """The lines printed at the end of a run: a few, or one."""
    used = summary["frames_used"]
    frames = f"{used} frame{'s' if used != 1 else ''} used, {summary['frames_dropped']} dropped"
    energy = ""
    if summary.get("energy_first") is not None:
        first, last = summary["energy_first"], summary["energy_last"]
        change = f" ({100 * (last - first) / first:+.1f} %)" if first else ""
        energy = f"energy {first:.6g} -> {last:.6g}{change}"
    time_memory = f"{summary['seconds']:.1f} s, peak memory {summary['peak_memory_mb']:.0f} MB"
    said = f"{summary['warnings']} warning{'s' if summary['warnings'] != 1 else ''}"
    where = summary.get("outputs")
    if one_line:
        return ["summary: " + "; ".join(p for p in (frames, energy, time_memory, said) if p)
                + (f"; wrote {where}" if where else "")]
    lines = [f"summary: {frames}" + (f"; {energy} at the finest level" if energy else ""),
             f"         {time_memory}; {said}" + (" (listed in report.json)" if summary["warnings"] else "")]
    if summary.get("input_checks"):
        flagged = summary.get("input_checks_flagged") or {}
        counts = ", ".join(f"{n} {status}{'s' if n != 1 and status != 'ok' else ''}"
                           + (f" ({', '.join(map(str, flagged[status]))})" if flagged.get(status) else "")
                           for status, n in summary["input_checks"].items())
        lines.insert(1, f"         input checks: {counts}")
    if where:
        lines.append(f"         report: {where}/report.json")
    return lines


def refinement_report(refinement, files: list | None = None) -> dict:
    """The report of a :class:`~o3d_mvps.Refinement` (the module docstring; keys :data:`REPORT_KEYS`)."""
    info = refinement.info
    poses = info.get("pose_updates")
    if poses is None and refinement.poses is not None and "initial_poses" in info:
        poses = pose_movement(info["initial_poses"], refinement.poses.numpy(), info.get("frames", []))
    stages = info.get("stage_peak_memory_mb") or {}
    report = {"method": refinement.method, "energy": refinement.energy,
              "energy_per_level": energy_per_level(refinement.energy), "timings": refinement.timings, "info": info,
              "inputs": info.get("inputs"), "frames": frames_report(info, files), "poses": poses,
              "light": info.get("light_selection") or info.get("light_model"), "residuals": info.get("residuals"),
              "device": info.get("device"), "peak_memory_mb": max(stages.values()) if stages else None,
              "warnings": list(info.get("warnings", []))}
    report["summary"] = summarise(report)
    return report


def reconstruction_report(info: dict, said: list, files: list | None = None) -> dict:
    """The report of a whole-object reconstruction (``Reconstruction.info`` and its keys at the
    top level, as before) with the keys of a refinement's that apply: method "reconstruct",
    frames (used by some reference view, or why not), device, peak_memory_mb (this process;
    ``workers_peak_memory_mb`` the Dask workers'), warnings and summary."""
    kept = info.get("registered_frames", [])
    used = sorted({kept[f] if f < len(kept) else f for view in info.get("views", []) for f in view.get("frames", [])})
    reasons = {int(i): why for i, why in info.get("dropped_frames", {}).items()}
    rows = frames_report({"frames": used, "capture_frames": info.get("capture_frames", len(kept)),
                          "dropped_frames": {i: reasons.get(i, "seen by no reference view (or too little)")
                                             for i in range(info.get("capture_frames", len(kept))) if i not in used}},
                         files)
    stages = info.get("stage_peak_memory_mb") or {}
    report = {"method": "reconstruct", **info, "frames": rows, "device": "cpu",
              "peak_memory_mb": max(stages.values()) if stages else peak_memory_mb(), "warnings": list(said)}
    report["summary"] = summarise(report)
    return report
