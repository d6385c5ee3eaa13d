"""Per level and per sweep: CPU seconds, energy, the sweep's depth/normal update and the accuracy
the solve would have if it stopped there (issue #31, sweep counts and stopping rules).

``python -m benchmarks.sweeps PROBLEM.npz CAPTURE OUT.json [--caps 10,10,5,5,5] [--tols ...] [--no-trace]``

PROBLEM is a saved solver input (``o3d-mvps refine CAPTURE OUT --save-problem PROBLEM.npz``: the
registration is not repeated), CAPTURE the rendered capture whose ``groundtruth/`` scores it.
``--caps`` / ``--tols`` override ``max_iterations`` / ``tolerance`` per level (index 0 = finest).
Run it from the tree to measure, with ``NUMBA_NUM_THREADS=1``. The driver is observed by wrapping
its private ``_sweeps`` (a level) and ``_extrapolate`` (a sweep's last step) and swapping its clock
for ``time.process_time``; the hooks' own CPU time (the accuracy of every sweep) is not counted.
"If stopped here" applies what the level's end applies (the sensor tie,
:func:`o3d_mvps.solver.weighting.tie_low_frequencies`), upsamples z bilinearly to the colour grid
and scores it with :func:`o3d_mvps.metrics.evaluate`; on the finest level that is the result.
On a coarser level ``mae_smooth_deg`` / ``rmse_smooth_mm`` score it once more without its grid
modes (:func:`without_grid_modes`): the depth that alternates from pixel to pixel, which the
level's central-difference normals do not see and the bilinear upsampling turns into ripples
the colour grid's normals do see (docs/performance.md, "Why level 1's error grows at 2 MP").

OUT: {"total_cpu", "accuracy", "n_sweeps", "levels": [{"level", "size", "sweeps", "cpu", "energy",
"steps" (CPU s per driver stage, the hooks' time taken out), "mae_deg", "rmse_mm"}], "sweeps": [{"level", "cpu", "energy",
"dz_mm" (RMS depth update), "dn_deg" (mean normal update), "mae_deg", "rmse_mm" and, on coarser
levels, "mae_smooth_deg", "rmse_smooth_mm"}]}.
:func:`plot_traces` draws such results (benchmarks/results/sweeps.png).
"""

from __future__ import annotations

import argparse
import json
import time
import types
from dataclasses import replace

import cv2
import numpy as np
from scipy import ndimage

from o3d_mvps.capture.reading import read_capture
from o3d_mvps.metrics import evaluate
from o3d_mvps.model.normals import perspective_normals
from o3d_mvps.model.resampling import fill_nearest_valid
from o3d_mvps.refinement import Refinement
from o3d_mvps.solver import driver
from o3d_mvps.solver.device import to_host
from o3d_mvps.solver.options import AUTO
from o3d_mvps.solver.problem_input import read_problem
from o3d_mvps.solver.weighting import lowpass_sigma, tie_low_frequencies


def _ints(text):
    return None if not text else [int(x) for x in text.split(",")]


def _floats(text):
    return None if not text else [float(x) for x in text.split(",")]


#: :func:`without_grid_modes`' 5-tap filter ``1 - [1, -4, 6, -4, 1] / 16``: frequency response
#: ``1 - sin^4(omega / 2)``, 0 at the grid's Nyquist frequency (a period of 2 pixels), 0.75 at a
#: period of 4 pixels, 0.98 at 8
GRID_MODE_TAPS = np.array([-1.0, 4.0, 10.0, 4.0, -1.0]) / 16.0


def without_grid_modes(z: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """z (H, W) metres filtered by :data:`GRID_MODE_TAPS` along rows, then columns, at the masked
    pixels whose five pixels in that direction are all masked (elsewhere, and outside ``mask``
    (H, W) bool, unchanged): without the depth that alternates from pixel to pixel
    (z[p+1] - z[p-1] = 0, unseen by central differences). Next to a depth step it rings by a
    16th of the step, which raises the depth RMSE there; the normals' error is what it is for."""
    out = np.asarray(z, dtype=np.float64)
    inside = np.asarray(mask, dtype=bool)
    for axis in (1, 0):
        full = inside & (ndimage.correlate1d(inside.astype(np.float64), np.ones(5), axis=axis, mode="constant") > 4.5)
        out = np.where(full, ndimage.correlate1d(out, GRID_MODE_TAPS, axis=axis, mode="nearest"), out)
    return out


def run(problem_file, capture, caps=None, tols=None, trace=True) -> dict:
    """Solve the saved problem once, observed; returns the OUT dictionary (module docstring)."""
    gt = read_capture(capture).groundtruth
    if gt is None:
        raise SystemExit(f"{capture}: no groundtruth/ folder; give a rendered capture")
    ctx, levels, rows, hook = {}, [], [], [0.0]
    solve0, sweeps0, extrapolate0 = driver._solve, driver._sweeps, driver._extrapolate

    def cpu():
        return time.process_time() - hook[0]

    def accuracy(problem, z):
        g = problem.level.grid
        zl = g.scatter(to_host(z))
        if ctx["sigma"] is not None:
            zl = tie_low_frequencies(zl, g.mask, ctx["z0"], ctx["sigma"])
        H, W = ctx["ref"].shape

        def score(depth):
            depth = fill_nearest_valid(depth, g.mask)
            up = depth if depth.shape == (H, W) else cv2.resize(depth, (W, H), interpolation=cv2.INTER_LINEAR)
            return evaluate(Refinement.from_arrays(np.where(ctx["ref"], up, 0.0), ctx["ref"], ctx["K"]), gt)

        out = score(zl)
        if zl.shape != (H, W):
            smooth = score(without_grid_modes(zl, g.mask))
            out.update(mae_smooth_deg=smooth["mae_deg"], rmse_smooth_mm=smooth["rmse_mm"])
        return out

    def update(problem, z1, z0):
        g, K = problem.level.grid, problem.level.K
        n1, _ = perspective_normals(g.scatter(to_host(z1)), K, g.mask)
        n0, _ = perspective_normals(g.scatter(to_host(z0)), K, g.mask)
        m = g.mask & np.any(n1 != 0, 2) & np.any(n0 != 0, 2)
        angle = np.degrees(np.arccos(np.clip((n1 * n0).sum(2)[m], -1, 1)))
        return float(np.sqrt(np.mean((to_host(z1) - to_host(z0)) ** 2)) * 1e3), float(angle.mean())

    def observed(fn, *args):
        start = time.process_time()
        out = fn(*args)
        hook[0] += time.process_time() - start
        return out

    def solve(pi, options, device):
        ref = driver._reference_mask(pi)
        z0 = pi.depths[0].astype(np.float64)
        s = options.model.lowpass_width()
        ctx.update(ref=ref, z0=z0, K=pi.K, sigma=lowpass_sigma(z0, ref, pi.scale_factor) if s == AUTO else s)
        return solve0(pi, options, device)

    def sweeps(problem, est, options, timings, stats, anchors=None, log=None, **settings):
        i = problem.level.index
        options = replace(options, **({"max_iterations": caps[i]} if caps else {}),
                          **({"tolerance": tols[i]} if tols else {}))
        before, hooked = dict(timings), hook[0]
        ctx["start"] = ctx["last"] = cpu()
        out = sweeps0(problem, est, options, timings, stats, anchors, log, **settings)
        steps = {k: v - before.get(k, 0.0) for k, v in timings.items() if v != before.get(k, 0.0)}
        if "extrapolation" in steps:  # the driver's clock around _extrapolate also ran the per-sweep hook
            steps["extrapolation"] -= hook[0] - hooked
        levels.append({"level": i, "size": list(problem.level.size), "sweeps": len(out) - 1,
                       "cpu": cpu() - ctx["start"], "energy": float(out[-1]["energy"]), "steps": steps})
        if trace:
            levels[-1].update(observed(accuracy, problem, est.z))
        return out

    def extrapolate(problem, est, ev, before, anchors=None, **kw):
        ev = extrapolate0(problem, est, ev, before, anchors, **kw)
        row = {"level": problem.level.index, "cpu": cpu() - ctx["last"], "energy": float(ev.energy)}
        if trace:
            row["dz_mm"], row["dn_deg"] = observed(update, problem, est.z, before.z)
            row.update(observed(accuracy, problem, est.z))
        rows.append(row)
        ctx["last"] = cpu()
        return ev

    clock = driver.time
    driver._solve, driver._sweeps, driver._extrapolate = solve, sweeps, extrapolate
    driver.time = types.SimpleNamespace(perf_counter=time.process_time)
    try:
        pi = read_problem(problem_file)
        t0 = cpu()
        out = driver.solve(pi, pi.options, "cpu")
        total = cpu() - t0
    finally:
        driver._solve, driver._sweeps, driver._extrapolate, driver.time = solve0, sweeps0, extrapolate0, clock
    return {"total_cpu": total, "accuracy": evaluate(Refinement.from_arrays(out.depth, out.mask, out.K), gt),
            "n_sweeps": sum(r["sweeps"] for r in levels), "levels": levels, "sweeps": rows}


def plot_traces(traces: dict, path) -> None:
    """One panel per capture ({name: run() result with the trace}): normal MAE (deg) if stopped
    after each sweep against the solve's cumulative CPU seconds, one colour per level (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(traces), figsize=(4.2 * len(traces), 3.4), squeeze=False)
    for ax, (name, result) in zip(axes[0], traces.items()):
        t = np.cumsum([r["cpu"] for r in result["sweeps"]])
        for level in sorted({r["level"] for r in result["sweeps"]}, reverse=True):
            at = [i for i, r in enumerate(result["sweeps"]) if r["level"] == level]
            ax.plot(t[at], [result["sweeps"][i]["mae_deg"] for i in at], "o-", ms=3, label=f"level {level}")
        final = result["accuracy"]["mae_deg"]
        ax.axhline(final * 1.01, color="grey", lw=0.8, ls="--", label="final +1 %")
        ax.set_ylim(final * 0.95, final * 1.6)
        ax.set_title(f"{name}: {result['n_sweeps']} sweeps")
        ax.set_xlabel("solve CPU s (cumulative)")
        ax.set_ylabel("normal MAE if stopped (deg)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("problem")
    ap.add_argument("capture")
    ap.add_argument("out")
    ap.add_argument("--caps", help="sweep cap per level, finest first (comma-separated)")
    ap.add_argument("--tols", help="relative energy tolerance per level, finest first")
    ap.add_argument("--no-trace", action="store_true", help="time only: no per-sweep accuracy")
    args = ap.parse_args(argv)
    result = run(args.problem, args.capture, _ints(args.caps), _floats(args.tols), not args.no_trace)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({"total_cpu": round(result["total_cpu"], 2), **result["accuracy"],
                      "sweeps": [r["sweeps"] for r in result["levels"]],
                      "level_cpu": [round(r["cpu"], 2) for r in result["levels"]]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
