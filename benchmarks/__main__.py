"""Benchmarks of o3d_mvps: ``python -m benchmarks {accuracy,frames,tau,speed,figures,all} [--quick] [--out DIR]``.

accuracy: every method on rendered captures (bunny, armadillo; SF 2/4/8; 640x480, 20 frames).
frames: error of ours against n in {5, ..., 30} (bunny, SF 4). tau: error against tau~.
speed: wall time and peak memory of odometry + refine at 640x480 / 160x120, 1280x720 / 640x360 (D415)
and 1708x1136 / 427x284 with 1M object pixels (about 2.5 min and 6 GB on two cores).
object: reconstruct rendered 360-degree rings with raw and refined depth; Chamfer, normals, 1/2 workers.
static: a static-camera, moving-light capture with the D415-like sensor: ours vs bicubic, normal MAE,
depth RMSE and the low-pass shape difference from the sensor depth (p95, per mille).
peers: a wide-baseline, dark-speckled, D415-like capture (room light and LED): ours against TSDF depth
fusion (4 and 2 mm voxels) and bicubic, scored as issue #32 item 7 scores (not part of 'all').
room: a table-and-wall scene (automatic masks), room-lit and LED-lit (--light): error and banding along
the 1 mm depth steps.
scaling: time, memory, sweeps and CG iterations against object pixels x frames (--baseline REV
runs an earlier commit side by side; not part of 'all': hours at the default sizes).
figures: README and docs pictures (normals of every method, textured preview).
gpu (python -m benchmarks.gpu make|run|count, not part of 'all'): the solver's CUDA path against the
CPU on saved problems, for a GPU machine without Open3D, and its device operations counted without a
GPU (see benchmarks/gpu.py).
stages (python -m benchmarks.stages, not part of 'all'): CPU seconds and peak memory of every refine
stage, this tree against a baseline checkout, alternating in the same run (speed_stages.json).
sweeps (python -m benchmarks.sweeps, not part of 'all'): per level and per sweep CPU seconds, energy,
update and accuracy if stopped there, of a saved problem (per-level caps and tolerances to try).
summary: no run; rebuild summary.md and every plot from the result files already in --out.
all: everything, one after the other. --quick runs a tiny case of each (CI, under a minute).
Results go to DIR (default benchmarks/results) as JSON, summary.md and PNG plots.
"""

from __future__ import annotations

import argparse

from . import accuracy, figures, object as object_study, peers, room, scaling, speed, static, studies
from .summary import write_summary

STUDIES = ("accuracy", "frames", "tau", "speed", "room", "figures")


def _run(name: str, args) -> None:
    if name == "accuracy":
        accuracy.run(args)
    elif name == "figures":
        figures.run(args)
    elif name == "speed":
        speed.run(args)
    elif name == "scaling":
        scaling.run(args)
    elif name == "object":
        object_study.run(args)
    elif name == "room":
        room.run(args)
    elif name == "static":
        static.run(args)
    elif name == "peers":
        peers.run(args)
    else:
        studies.run(args, name)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quick", action="store_true", help="tiny sizes (CI, under a minute)")
    common.add_argument("--out", default="benchmarks/results", help="results folder")
    sub = parser.add_subparsers(dest="command", required=True)
    accuracy.add_arguments(sub.add_parser("accuracy", parents=[common], help="all methods, all cases"))
    studies.add_arguments(sub.add_parser("frames", parents=[common], help="error against n"), "frames")
    studies.add_arguments(sub.add_parser("tau", parents=[common], help="error against tau~"), "tau")
    speed.add_arguments(sub.add_parser("speed", parents=[common], help="time and peak memory"))
    scaling.add_arguments(sub.add_parser("scaling", parents=[common],
                                         help="time against object pixels x frames, against a baseline revision"))
    object_study.add_arguments(sub.add_parser("object", parents=[common],
                                              help="whole-object reconstruction on 360-degree rings, raw vs refined"))
    room.add_arguments(sub.add_parser("room", parents=[common],
                                      help="a scene under room light and the LED: error and banding along the 1 mm depth steps"))
    static.add_arguments(sub.add_parser("static", parents=[common],
                                        help="static camera, moving light, D415-like sensor: ours vs bicubic"))
    peers.add_arguments(sub.add_parser("peers", parents=[common],
                                       help="wide-baseline noisy speckled capture: ours vs TSDF fusion and bicubic"))
    figures.add_arguments(sub.add_parser("figures", parents=[common], help="README and docs pictures (normals, preview)"))
    sub.add_parser("all", parents=[common], help="every benchmark with its defaults")
    sub.add_parser("summary", parents=[common], help="no run: rebuild summary.md and the plots from the results in --out")
    args = parser.parse_args(argv)
    if args.command == "all":
        for name in STUDIES:
            _run(name, parser.parse_args([name, *(["--quick"] if args.quick else []), "--out", args.out]))
    elif args.command != "summary":
        _run(args.command, args)
    print(f"wrote {write_summary(args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
