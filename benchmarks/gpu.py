"""The solver's CUDA path against its CPU path on the same saved problems, in the same run.

Two steps, for a GPU machine without Open3D (the problems travel as files):

- ``python -m benchmarks.gpu make DIR`` (here, with Open3D): renders the bunny under the LED,
  20 frames, at 640x480 / 160x120 and at the D415's 1280x720 / 640x360, and writes each solver
  input as a saved problem (``DIR/gpu_WxH.npz``, true poses, the colour as 8-bit codes as a read
  capture holds it; 10 and 30 MB with the renders' sensor noise, 14 and 43 MB saved decoded).
- ``python -m benchmarks.gpu run DIR [--out benchmarks/results]`` (on the GPU machine): solves
  each on the CPU once and on ``cuda:0`` twice (the first run compiles the CUDA kernels), once
  more there from the frames decoded first, and writes ``gpu.json``: rows {color, depth, frames,
  object_pixels, device (the GPU's name), seconds (solve, after warm-up), seconds_first (with
  compilation), seconds_float (the frames decoded before the solve), cpu_seconds (the CPU solve,
  same machine, same run), peak_gpu_mb, max_depth_diff_mm, mae_diff_deg, energy_rel_diff (the
  largest over every sweep's energy), coded_vs_float (the same three of the two GPU solves),
  level_devices (where each level ran, coarsest first: levels below
  o3d_mvps.solver.device.CUDA_MIN_LEVEL_PIXELS run on the CPU)}.

``run(..., device=ArrayDevice)`` takes another array device instead of cuda:0 (its test: the CuPy
stand-in of tests/cupy_emulation.py; no memory counted, times meaningless).

- ``python -m benchmarks.gpu levels DIR [--out benchmarks/results]`` (on the GPU machine): each
  saved problem solved on the CPU, on cuda:0 with every level there, and with the product's split
  (CUDA_MIN_LEVEL_PIXELS), twice each after a warm-up; writes ``gpu_levels.json``: per problem
  and case, each run's total seconds, each level's sweep seconds (the device synchronised
  before and after), the levels' devices, the difference to the CPU's solve (as ``run``'s) and
  every sweep's energy: the data for CUDA_MIN_LEVEL_PIXELS and for where the paths part.

- ``python -m benchmarks.gpu count DIR [--out benchmarks/results]`` (anywhere, no GPU): counts the
  CUDA path's device operations (kernel launches and copies, each costing 5-20 us from Python on
  a GPU however small the level) per pyramid level and sweep, on that stand-in, with the CPU's
  kernels standing in for the CUDA ones (one launch per call) and the CUDA path's levels (those
  below CUDA_MIN_LEVEL_PIXELS on the CPU); writes ``gpu_counts.json``: per problem the totals by
  kind, launches (every operation but the copies) and transfers (copies either way), and per
  level the operations, launches and transfers per sweep and each sweep's CG iterations
  (``cg_iterations``), the commit counted, the linear solves
  and their host reads (copies to the host) each; with ``baseline`` the totals of
  ``gpu_operations.json`` (the counts at aacda76) and their ratio, with ``previous`` the counts
  of the ``gpu_counts.json`` it overwrites (launches and transfers, per sweep of each device
  level) and the ratios to them.
- ``python -m benchmarks.gpu sites DIR [--level 0] [--out DIR]``: the same count, and a Markdown
  table of where one level's sweeps spend their launches and copies: per function of o3d_mvps
  (``file function``, line numbers summed) and kernel (``[name]`` of a fused or compiled kernel),
  per sweep; with ``--out`` it also writes ``gpu_counts.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: (colour size (W, H), scale factor) of the cases: the speed benchmark's 640x480 and D415 sizes.
CASES = (((640, 480), 4), ((1280, 720), 2))
FRAMES = 20


def make(folder, cases=CASES, frames: int = FRAMES, options: dict | None = None) -> list[Path]:
    """Render each case and write its solver input (true poses) to ``folder``/gpu_WxH.npz, the
    colour as the 8-bit sRGB codes a read capture holds (saved-problem format 2)."""
    from dataclasses import replace

    from o3d_mvps import RefineOptions
    from o3d_mvps.solver.problem_input import write_problem
    from o3d_mvps.solving import problem_from_capture
    from o3d_mvps.synthetic import render_capture

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for (w, h), sf in cases:
        capture = render_capture("bunny", frames=frames, scale_factor=sf, size=(w, h), seed=0, progress=False)
        problem, _ = problem_from_capture(capture, RefineOptions(progress=False, **(options or {})),
                                          capture.groundtruth.poses)
        problem = replace(problem, colors=srgb8_coded(problem.colors))
        paths.append(write_problem(problem, folder / f"gpu_{w}x{h}.npz", overwrite=True))
    return paths


def srgb8_coded(colors):
    """Float frames (n, H, W, 3) whose values are all decoded 8-bit sRGB codes (the renderer's
    camera) as the :class:`~o3d_mvps.colour.CodedColours` of those codes; ValueError otherwise."""
    from o3d_mvps.colour import CodedColours, decode_table

    table = decode_table(8)
    coded = []
    for frame in colors:
        codes = np.clip(np.searchsorted(table, frame), 0, table.size - 1).astype(np.uint8)
        if not np.array_equal(table[codes], frame):
            raise ValueError("the frames hold values that are not 8-bit sRGB codes: save them as floats")
        coded.append(codes)
    return CodedColours.from_codes(coded)


def _cuda_solver(device):
    """(solve on ``device``, its name, release the memory pool, the MB it holds): on a GPU
    ("cuda:0", or its ArrayDevice), the GPU's name and CuPy's pool; on a stand-in's
    ArrayDevice, its name and no memory."""
    from o3d_mvps.solver.device import array_device
    from o3d_mvps.solver.driver import solve

    device = array_device(device)

    def solve_on_device(problem):
        return solve(problem, device=device)

    if not hasattr(device.xp, "get_default_memory_pool"):  # not CuPy
        return solve_on_device, device.name, lambda: None, lambda: 0.0
    cupy = device.xp
    pool = cupy.get_default_memory_pool()
    name = cupy.cuda.runtime.getDeviceProperties(0)["name"]
    return (solve_on_device, name.decode() if isinstance(name, bytes) else name, pool.free_all_blocks,
            lambda: pool.total_bytes() / 2**20)


def compare(cpu, cuda) -> dict:
    """max_depth_diff_mm, mae_diff_deg (normals of the two depths) and energy_rel_diff of two
    solver outputs of one problem."""
    from o3d_mvps.metrics import normal_mae_deg
    from o3d_mvps.model.normals import perspective_normals

    mask = cpu.mask
    n_cpu, _ = perspective_normals(cpu.depth, cpu.K, mask)
    n_cuda, _ = perspective_normals(cuda.depth, cuda.K, mask)
    e_cpu = np.array([r["energy"] for r in cpu.energy])
    e_cuda = np.array([r["energy"] for r in cuda.energy])
    same_rows = len(e_cpu) == len(e_cuda)
    return {"max_depth_diff_mm": 1e3 * float(np.abs(cuda.depth - cpu.depth)[mask].max()),
            "mae_diff_deg": normal_mae_deg(n_cuda, n_cpu, mask),
            "energy_rel_diff": float(np.abs(e_cuda / e_cpu - 1).max()) if same_rows else None,
            "sweeps_cpu": len(e_cpu), "sweeps_cuda": len(e_cuda)}


def run(folder, out="benchmarks/results", device="cuda:0") -> list[dict]:
    """Solve every saved problem of ``folder`` on the CPU and on ``device`` (the CUDA path),
    there also from its frames decoded first; writes ``out``/gpu.json after each and returns its rows."""
    from dataclasses import replace

    from o3d_mvps.solver.driver import solve
    from o3d_mvps.solver.problem_input import read_problem

    paths = sorted(Path(folder).glob("gpu_*.npz"))
    if not paths:
        raise SystemExit(f"no gpu_*.npz saved problems in {folder}: make them with python -m benchmarks.gpu make")
    solve_cuda, device_name, release_memory, held_mb = _cuda_solver(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in paths:
        problem = read_problem(path)
        t = time.perf_counter()
        cpu = solve(problem)
        cpu_seconds = time.perf_counter() - t
        release_memory()
        t = time.perf_counter()
        solve_cuda(problem)  # compiles the CUDA kernels (they are not cached on disk)
        seconds_first = time.perf_counter() - t
        # CuPy's pool gives nothing back during a solve (freed blocks return to the pool): what it
        # holds after one from empty is the solve's high-water mark (numba's few partial sums aside)
        peak_gpu_mb = held_mb()
        t = time.perf_counter()
        cuda = solve_cuda(problem)
        seconds = time.perf_counter() - t
        # the same frames decoded first: a GPU level decodes coded frames on upload, so only the
        # device's own run-to-run differences (its atomic sums' order) may part the two
        t = time.perf_counter()
        decoded = solve_cuda(replace(problem, colors=problem.float_colors()))
        seconds_float = time.perf_counter() - t
        (h, w), depth = problem.color_size, problem.depths[0].shape
        rows.append({"color": f"{w}x{h}", "depth": f"{depth[1]}x{depth[0]}", "frames": problem.n_frames,
                     "object_pixels": int(cpu.mask.sum()), "device": device_name, "seconds": seconds,
                     "seconds_first": seconds_first, "seconds_float": seconds_float, "cpu_seconds": cpu_seconds,
                     "peak_gpu_mb": peak_gpu_mb, **compare(cpu, cuda), "coded_vs_float": compare(decoded, cuda),
                     "level_devices": cuda.info["level_devices"]})
        (out / "gpu.json").write_text(json.dumps(rows, indent=1))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def levels(folder, out="benchmarks/results", device="cuda:0", repeats: int = 2, warm_up: bool = True) -> dict:
    """Per-level sweep seconds of every saved problem of ``folder`` on the CPU and on ``device``
    (every level there, and the product's split), each ``repeats`` times after a ``warm_up``
    solve; see the module's docstring. Writes ``out``/gpu_levels.json after each case and
    returns its content."""
    from dataclasses import replace

    from o3d_mvps.solver import driver
    from o3d_mvps.solver.device import array_device
    from o3d_mvps.solver.problem_input import read_problem

    device = array_device(device)
    cuda = getattr(device.xp, "cuda", None)  # None on the stand-in: nothing to wait for
    records, sweeps = [], driver._sweeps

    def synchronize():
        if cuda is not None:
            cuda.Device().synchronize()

    def timed_sweeps(problem, *args, **kwargs):
        synchronize()
        t = time.perf_counter()
        result = sweeps(problem, *args, **kwargs)
        synchronize()
        records.append({"level": problem.level.index, "pixels": int(problem.level.grid.size),
                        "sweeps": len(result), "seconds": time.perf_counter() - t})
        return result

    cases = {"cpu": "cpu", "device_all": replace(device, min_level_pixels=0), "device_product": device}
    results = {"device": _cuda_solver(device)[1], "problems": {}}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    driver._sweeps = timed_sweeps
    try:
        for path in sorted(Path(folder).glob("gpu_*.npz")):
            problem, cpu, rows = read_problem(path), None, results["problems"].setdefault(path.name, {})
            for name, case in cases.items():
                if warm_up:
                    driver.solve(problem, device=case)  # compiles or loads the kernels
                for _ in range(repeats):
                    records.clear()
                    t = time.perf_counter()
                    result = driver.solve(problem, device=case)
                    total = time.perf_counter() - t
                    cpu = result if cpu is None else cpu
                    rows.setdefault(name, []).append({
                        "seconds": total, "levels": list(records), "level_devices": result.info["level_devices"],
                        "against_cpu": compare(cpu, result),
                        "energies": [[r["level"], r["iteration"], r["energy"]] for r in result.energy]})
                    print(path.name, name, f"{total:.2f} s", [(r["pixels"], round(r["seconds"], 3)) for r in records],
                          flush=True)
                (out / "gpu_levels.json").write_text(json.dumps(results, indent=1))
    finally:
        driver._sweeps = sweeps
    return results


def count(folder, out="benchmarks/results", min_level_pixels: int | None = None, sites: bool = False) -> list[dict]:
    """Count the CUDA path's device operations on every saved problem of ``folder`` (see the
    module's docstring); writes ``out``/gpu_counts.json and returns its rows: problem,
    object_pixels, operations (total), launches, transfers and by_kind, and per level (coarsest
    first) its pixels, device, sweeps and the operations, launches and transfers of its sweeps,
    in all and per sweep (the levels' set-up and the copies between levels count in the totals
    only). min_level_pixels: the CUDA path's smallest level on the device (None: the product's,
    CUDA_MIN_LEVEL_PIXELS). sites: also count by call site and kernel (slower), each level's
    sweeps in its ``sites``: {(kind, "file function [kernel]"): operations} (not in the JSON)."""
    tests = str(Path(__file__).resolve().parents[1] / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import cupy_emulation

    from o3d_mvps.solver import driver, krylov, linear
    from o3d_mvps.solver.device import CUDA_MIN_LEVEL_PIXELS
    from o3d_mvps.solver.problem_input import read_problem

    paths = sorted(Path(folder).glob("*.npz"))
    if not paths:
        raise SystemExit(f"no saved problems (*.npz) in {folder}")
    levels = []
    solve_level_sweeps = driver._sweeps

    def counted_sweeps(problem, *args, **kwargs):
        kinds = cupy_emulation.operations
        before, copies_before = sum(kinds.values()), kinds["to_host"] + kinds["to_device"]
        sites_before = cupy_emulation.sites.copy()
        rows = solve_level_sweeps(problem, *args, **kwargs)
        operations, transfers = sum(kinds.values()) - before, kinds["to_host"] + kinds["to_device"] - copies_before
        levels.append({"level": problem.level.index, "pixels": problem.level.grid.size, "sweeps": len(rows) - 1,
                       "operations": operations, "launches": operations - transfers, "transfers": transfers,
                       "cg_iterations": [row.get("cg_iterations") for row in rows[1:]]})
        if sites:
            levels[-1]["sites"] = cupy_emulation.sites - sites_before
        return rows

    baseline_file = Path(out) / "gpu_operations.json"
    baseline = ({row["problem"]: row["operations"] for row in json.loads(baseline_file.read_text())}
                if baseline_file.is_file() else {})
    previous_file = Path(out) / "gpu_counts.json"  # the last count, before this one overwrites it
    previous = ({row["problem"]: row for row in json.loads(previous_file.read_text())}
                if previous_file.is_file() else {})
    solves = []  # the host reads (copies to the host) of each linear solve
    pcg = krylov.pcg

    def counted_pcg(*args, **kwargs):
        before = cupy_emulation.operations["to_host"]
        result = pcg(*args, **kwargs)
        solves.append(cupy_emulation.operations["to_host"] - before)
        return result

    results = []
    driver._sweeps, krylov.pcg = counted_sweeps, counted_pcg
    recording = cupy_emulation.recording_sites() if sites else _nothing()
    try:
        with cupy_emulation.installed(), _cpu_kernels_as_cuda_kernels(cupy_emulation), recording:
            for path in paths:
                levels.clear()
                solves.clear()
                cupy_emulation.operations.clear()
                linear._CG_ITERATIONS.clear()  # CG's first status read: the same guesses in every count
                device = cupy_emulation.array_device(CUDA_MIN_LEVEL_PIXELS if min_level_pixels is None
                                                     else min_level_pixels)
                solution = driver.solve(read_problem(path), device=device)
                for level, where in zip(levels, solution.info["level_devices"]):
                    level["device"] = where
                    for name in ("operations", "launches", "transfers"):
                        level[f"{name}_per_sweep"] = round(level[name] / max(level["sweeps"], 1), 1)
                cupy_emulation.sites.clear()
                kinds = cupy_emulation.operations
                total, transfers = sum(kinds.values()), kinds["to_host"] + kinds["to_device"]
                results.append({"problem": path.name, "commit": _commit(), "object_pixels": int(solution.mask.sum()),
                                "operations": total,
                                "launches": total - transfers, "transfers": transfers,
                                "by_kind": dict(kinds.most_common()), "levels": list(levels),
                                "linear_solves": len(solves), "host_reads_per_linear_solve": {
                                    "max": max(solves, default=0),
                                    "mean": round(sum(solves) / max(len(solves), 1), 2)},
                                **({"baseline": {"commit": "aacda76", "operations": baseline[path.name],
                                                 "ratio": round(total / baseline[path.name], 3)}}
                                   if path.name in baseline else {}),
                                **({"previous": _compared(previous[path.name], total - transfers, transfers, levels)}
                                   if path.name in previous else {})})
                print(json.dumps(_without_sites(results[-1])), flush=True)
    finally:
        driver._sweeps, krylov.pcg = solve_level_sweeps, pcg
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "gpu_counts.json").write_text(json.dumps([_without_sites(row) for row in results], indent=1))
    return results


def _without_sites(row: dict) -> dict:
    """A row of :func:`count` without its levels' ``sites`` (JSON-ready)."""
    return {**row, "levels": [{k: v for k, v in level.items() if k != "sites"} for level in row["levels"]]}


@contextmanager
def _nothing():
    yield


def breakdown(level: dict) -> list[tuple[str, float, float]]:
    """Where one level's sweeps (a level row of :func:`count` with ``sites=True``) spent their
    operations: rows (``file function [kernel]``, launches per sweep, copies per sweep), most
    first, call sites of one function summed (line numbers dropped)."""
    launches, copies = Counter(), Counter()
    for (kind, site), n in level["sites"].items():
        where, _, kernel = site.partition(" [")
        path_line, _, function = where.partition(" ")
        key = f"{path_line.split(':')[0]} {function}" + (f" [{kernel}" if kernel else "")
        (copies if kind in ("to_host", "to_device") else launches)[key] += n
    sweeps = max(level["sweeps"], 1)
    return sorted(((key, launches[key] / sweeps, copies[key] / sweeps) for key in set(launches) | set(copies)),
                  key=lambda row: (-row[1] - row[2], row[0]))


def sites_table(folder, level_index: int = 0, out=None) -> str:
    """A Markdown table of :func:`breakdown` for level ``level_index`` of each saved problem of
    ``folder`` (counted as :func:`count` does; its JSON written to ``out``, None: a temporary folder)."""
    import tempfile

    lines = []
    with tempfile.TemporaryDirectory() as temporary:
        for row in count(folder, out=temporary if out is None else out, sites=True):
            level = next(level for level in row["levels"] if level["level"] == level_index)
            lines += [f"{row['problem']}, level {level_index}: {level['launches_per_sweep']} launches, "
                      f"{level['transfers_per_sweep']} copies per sweep ({level['sweeps']} sweeps)", "",
                      "| where (file function [kernel]) | launches per sweep | copies per sweep |", "|---|---|---|"]
            lines += [f"| {key} | {n:.1f} | {c:.1f} |" for key, n, c in breakdown(level)]
            lines.append("")
    return "\n".join(lines)


def _commit() -> str:
    """This checkout's commit (short hash, "+" where the work tree differs from it), or "?"."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"
    return head + ("+" if dirty else "")


def _compared(previous: dict, launches: int, transfers: int, levels: list) -> dict:
    """The previous count of a problem (its row of gpu_counts.json) beside this one: launches and
    transfers in all and per sweep of each level on the device, and this count's ratio to it."""
    before = {level["level"]: level for level in previous["levels"]}
    per_level = [{"level": level["level"], **{f"{name}_per_sweep": before[level["level"]][f"{name}_per_sweep"]
                                              for name in ("launches", "transfers")},
                  **{f"{name}_ratio": round(level[f"{name}_per_sweep"] / before[level["level"]][f"{name}_per_sweep"], 3)
                     for name in ("launches", "transfers")}}
                 for level in levels if level["device"] != "cpu" and before.get(level["level"], {}).get("launches")]
    return {"commit": previous.get("commit", "0ece6d0"), "launches": previous["launches"],
            "transfers": previous["transfers"], "launches_ratio": round(launches / previous["launches"], 3),
            "transfers_ratio": round(transfers / previous["transfers"], 3), "levels": per_level}


@contextmanager
def _cpu_kernels_as_cuda_kernels(stand_in):
    """Within: ``o3d_mvps.solver.cuda_kernels`` is a module of the CPU kernels taking the
    stand-in's arrays, each call counted in ``stand_in.operations`` as a launch (numba's CUDA
    simulator would take hours at these sizes)."""
    import o3d_mvps.solver
    from o3d_mvps.solver import cuda_kernels, kernels

    def launcher(kernel, name):
        def launch(*args):
            stand_in.count("kernel", name=name)
            return kernel(*(stand_in.host_data(a) for a in args))
        return launch

    module = types.ModuleType(cuda_kernels.__name__)
    module.__dict__.update({name: launcher(getattr(kernels, name), name) for name in cuda_kernels.__all__})
    module.trial_blocks = kernels.trial_blocks  # not launches
    module.lighting_blocks = kernels.lighting_blocks
    module.joint_blocks = kernels.joint_blocks
    sys.modules[module.__name__] = o3d_mvps.solver.cuda_kernels = module
    try:
        yield
    finally:
        sys.modules[module.__name__] = o3d_mvps.solver.cuda_kernels = cuda_kernels


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("make", help="render the cases and write saved problems (needs Open3D)").add_argument("folder")
    runner = sub.add_parser("run", help="solve the saved problems on the CPU and on cuda:0; write gpu.json")
    runner.add_argument("folder")
    runner.add_argument("--out", default="benchmarks/results")
    timer = sub.add_parser("levels", help="per-level seconds on the CPU and on cuda:0; write gpu_levels.json")
    timer.add_argument("folder")
    timer.add_argument("--out", default="benchmarks/results")
    counter = sub.add_parser("count", help="count the CUDA path's device operations on the CuPy stand-in (no GPU)")
    counter.add_argument("folder")
    counter.add_argument("--out", default="benchmarks/results")
    where = sub.add_parser("sites", help="count as count does, and print where one level's sweeps spend their "
                                         "launches and copies (by call site and kernel)")
    where.add_argument("folder")
    where.add_argument("--level", type=int, default=0)
    where.add_argument("--out", default=None, help="also write gpu_counts.json there (default: not kept)")
    args = parser.parse_args(argv)
    if args.command == "make":
        for path in make(args.folder):
            print(f"wrote {path} ({os.path.getsize(path) / 2**20:.1f} MB)")
    elif args.command == "run":
        run(args.folder, args.out)
    elif args.command == "levels":
        levels(args.folder, args.out)
    elif args.command == "sites":
        print(sites_table(args.folder, args.level, args.out))
    else:
        count(args.folder, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
