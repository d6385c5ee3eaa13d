"""Time one package tree's frame registration on a capture folder (a worker of ``benchmarks speed --registration``).

Run as a script, not a module, so that the package comes from the tree named on the command line
and not from the benchmarks' own checkout: ``python benchmarks/registration_worker.py TREE CAPTURE``.
Prints one JSON line: {"seconds", "cpu_seconds", "peak_mb", "frames", "dropped", "deg", "mm"} with
each registered frame's rotation (deg) and translation (mm) error against the capture's
``groundtruth/poses.npy``; ``peak_mb`` includes reading the capture.
"""

from __future__ import annotations

import json
import resource
import sys
import time
import warnings


def peak_rss_mb() -> float:
    """This process's peak resident set size in MiB: ``VmHWM`` of ``/proc/self/status``, the
    high-water mark of this program's own memory. (Linux's ``getrusage`` ``ru_maxrss`` also
    counts the parent's size at the fork that started this process: a worker started by a
    benchmark that had rendered a 2-megapixel capture reported the parent's gigabytes.) Falls
    back to ``ru_maxrss`` where /proc is missing (macOS: bytes there, not KiB)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def main(tree: str, folder: str) -> dict:
    """Register the capture ``folder`` with the package of ``tree``; timings and pose errors."""
    sys.path.insert(0, tree)
    import numpy as np

    from o3d_mvps.capture import read_capture
    from o3d_mvps.model import se3
    from o3d_mvps.odometry import register_frames

    capture = read_capture(folder)
    truth = se3.relative_to_reference(np.load(f"{folder}/groundtruth/poses.npy"))
    wall, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dropped frames are reported in the row
        result = register_frames(capture)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    errors = np.array([se3.pose_error(result.poses[k], truth[i]) for k, i in enumerate(result.frames) if i])
    return {"seconds": wall, "cpu_seconds": cpu, "peak_mb": peak_rss_mb(), "frames": result.frames,
            "dropped": sorted(result.dropped), "deg": np.round(errors[:, 0], 3).tolist(),
            "mm": np.round(errors[:, 1] * 1000, 2).tolist()}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2])))
