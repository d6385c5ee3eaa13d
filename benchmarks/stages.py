"""CPU time and peak memory of every refine stage, this tree against another, in the same run.

``python -m benchmarks.stages --baseline-tree DIR --captures d415=FOLDER 2mp=FOLDER [--repeats 2]``

Each capture is refined (odometry + ``refine``, default options) by a fresh process of each tree
in turn, alternating (baseline, this, baseline, this, ...), so that both see the same load. The
worker is this file run as a script with the tree on the command line (as
:mod:`.registration_worker`), so each run imports its own tree's package. In the worker,

- ``Refinement.timings`` are CPU seconds (all threads of the process): the driver's and the
  odometry's clock is swapped for ``time.process_time``, which other processes on a loaded
  machine do not inflate the way they inflate wall time;
- every stage's peak resident memory is its own: the kernel's high-water mark (``VmHWM``) is
  reset (``/proc/self/clear_refs``) before each call of a stage's function and read after it.

Rows of ``speed_stages.json``: {"capture", "version", "run", "cpu_seconds" (the whole
process), "refine_wall_seconds", "import_seconds", "read_seconds", "timings" (CPU seconds per
stage), "stage_peak_mb", "peak_mb", "energy", "sweeps", "baseline_revision" (the baseline tree's
commit), "numba_threads"}; ``speed_stages.png`` plots each
stage's CPU seconds per version (matplotlib).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

#: (module, function, stage) whose calls the worker times for their own peak memory
STAGE_FUNCTIONS = (("solving", "problem_from_capture", "odometry"),
                   ("solver.driver", "select_light_model", "light_selection"),
                   ("solver.driver", "build_level", "build_level"), ("solver.driver", "update_albedo", "albedo"),
                   ("solver.driver", "refit_albedo", "albedo"),
                   ("solver.driver", "update_lighting", "lighting"),
                   ("solver.driver", "_extrapolate", "extrapolation"),
                   ("solver.driver", "update_poses", "poses"), ("solver.driver", "update_depth", "depth"),
                   ("solver.driver", "update_pose_depth", "poses_depth"),
                   ("solver.driver", "_tie_to_sensor", "sensor_tie"))


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) / 1024.0 for line in status if line.startswith(key))


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current resident size


def worker(tree: str, folder: str, options: dict) -> dict:
    """Refine the capture ``folder`` with the package of ``tree``; the row of this run."""
    import importlib
    import resource
    import types

    sys.path.insert(0, tree)
    t = time.perf_counter()
    from o3d_mvps import RefineOptions, refine
    from o3d_mvps.capture import read_capture

    import_seconds = time.perf_counter() - t
    import numba

    cpu_clock = types.SimpleNamespace(perf_counter=time.process_time)
    peaks: dict[str, float] = {}
    for module_name, name, stage in STAGE_FUNCTIONS:
        module = importlib.import_module(f"o3d_mvps.{module_name}")
        module.time = cpu_clock
        function = getattr(module, name, None)
        if function is None:  # an older tree without this stage (aacda76: no light selection, no sensor tie)
            continue

        def timed(*args, _function=function, _stage=stage, **kwargs):
            _reset_peak()
            try:
                return _function(*args, **kwargs)
            finally:
                peaks[_stage] = max(peaks.get(_stage, 0.0), _status_mb("VmHWM:"))
                _reset_peak()

        setattr(module, name, timed)
    t = time.perf_counter()
    capture = read_capture(folder)
    read_seconds = time.perf_counter() - t
    peaks["read"] = _status_mb("VmRSS:")
    t = time.perf_counter()
    handed = [capture]  # handed over as the command line does: refine lets go of it once the solver's input is made
    del capture
    result = refine(handed.pop(), RefineOptions(progress=False, **options))
    wall = time.perf_counter() - t
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"cpu_seconds": usage.ru_utime + usage.ru_stime, "refine_wall_seconds": wall,
            "import_seconds": import_seconds, "read_seconds": read_seconds, "timings": result.timings,
            "stage_peak_mb": peaks, "peak_mb": max(peaks.values()), "energy": result.energy[-1]["energy"],
            "sweeps": len([row for row in result.energy if row["iteration"] > 0]),
            "numba_threads": numba.get_num_threads()}


def run_one(tree: Path, folder: Path, options: dict) -> dict:
    """:func:`worker` in a fresh process (this file run as a script)."""
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(tree), str(folder),
                           json.dumps(options)], capture_output=True, text=True, check=False, cwd=tree)
    if done.returncode != 0:
        raise RuntimeError(f"stage worker failed in {tree} ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(args) -> list[dict]:
    """Every capture x repeat x version (baseline first), alternating; writes the JSON after each."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    trees = {"baseline": Path(args.baseline_tree).resolve(), "this": Path(__file__).resolve().parent.parent}
    revision = subprocess.run(["git", "-C", str(trees["baseline"]), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=False).stdout.strip() or None
    rows = []
    for entry in args.captures:
        name, folder = entry.split("=", 1)
        for k in range(args.repeats):
            for version, tree in trees.items():
                row = {"capture": name, "version": version, "run": k, **run_one(tree, Path(folder), args.options),
                       "baseline_revision": revision}
                rows.append(row)
                print(f"{name} [{version}] run {k}: {row['cpu_seconds']:.1f} CPU s, peak {row['peak_mb']:.0f} MB",
                      flush=True)
                (out / "speed_stages.json").write_text(json.dumps(rows, indent=1))
    plot(rows, out / "speed_stages.png")
    return rows


#: the stages plotted, in pipeline order
STAGES = ("odometry", "light_selection", "setup", "evidence_weights", "albedo_lighting", "extrapolation", "poses",
          "depth", "poses_depth")


def plot(rows: list[dict], path: Path) -> None:
    """Per capture, each stage's CPU seconds (the least over the repeats) per version, as bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    captures = list(dict.fromkeys(r["capture"] for r in rows))
    versions = list(dict.fromkeys(r["version"] for r in rows))
    fig, axes = plt.subplots(1, len(captures), figsize=(6 * len(captures), 4), squeeze=False)
    for ax, capture in zip(axes[0], captures):
        width = 0.8 / len(versions)
        for k, version in enumerate(versions):
            mine = [r for r in rows if r["capture"] == capture and r["version"] == version]
            seconds = [min(r["timings"].get(s, 0.0) for r in mine) for s in STAGES]
            peak = min(r["peak_mb"] for r in mine)
            ax.bar(np.arange(len(STAGES)) + k * width, seconds, width, label=f"{version} (peak {peak:.0f} MB)")
        ax.set_xticks(np.arange(len(STAGES)) + 0.4 - width / 2, STAGES, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("CPU seconds (all threads)")
        ax.set_title(capture)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.stages", description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline-tree", required=True, help="a checkout of the baseline revision (git worktree add)")
    parser.add_argument("--captures", nargs="+", required=True, metavar="NAME=FOLDER",
                        help="capture folders (write_capture of render_capture), e.g. d415=/tmp/d415")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--options", type=json.loads, default={}, help="RefineOptions as JSON (default: the defaults)")
    parser.add_argument("--out", default="benchmarks/results")
    return 0 if run(parser.parse_args(argv)) else 1


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], sys.argv[3], json.loads(sys.argv[4])), default=float))
        raise SystemExit(0)
    raise SystemExit(main())
