"""The ``--overwrite`` option of the subcommands (outputs are checked before any work, and the
refusal names the command-line flag), what ``--quiet`` silences, the solver's log of what it did
and the summary printed at the end of a run."""

from __future__ import annotations

import warnings
from contextlib import contextmanager

from ..fileio import check_output_files, check_output_folder
from ..run_report import summary_lines

OVERWRITE_FLAG = "--overwrite"


def add_overwrite_argument(parser, what: str) -> None:
    """Add ``--overwrite`` to a subcommand writing ``what`` (e.g. "output folder")."""
    parser.add_argument(OVERWRITE_FLAG, action="store_true",
                        help=f"write into an existing {what}, replacing only what this command writes there")


def check_folder(path, overwrite: bool, what: str, inputs=()):
    """Absolute path of the output folder; OutputExistsError (naming --overwrite) if it would replace
    files, OutputPathError if it cannot be written or is (inside) one of ``inputs``
    (:func:`o3d_mvps.fileio.check_output_folder`)."""
    return check_output_folder(path, overwrite, what=what, flag=OVERWRITE_FLAG, inputs=inputs)


def check_files(paths, overwrite: bool, inputs=()) -> list:
    """The output paths; OutputExistsError (naming --overwrite) if one exists and not ``overwrite``,
    OutputPathError if one is a folder, cannot be written or is one of ``inputs``."""
    return check_output_files(paths, overwrite, flag=OVERWRITE_FLAG, inputs=inputs)


@contextmanager
def quiet_output(quiet: bool):
    """Under ``quiet``: Python warnings are not printed (they are still recorded for report.json
    and counted in the summary), Open3D logs errors only, Dask's loggers errors only (no
    "Sending large graph", socket or shutdown notices). Restored on exit."""
    if not quiet:
        yield
        return
    from ..reconstruct.parallel import quiet_dask, quiet_open3d

    quiet_open3d()
    quiet_dask()
    with warnings.catch_warnings():
        warnings.showwarning = lambda *args, **kwargs: None
        yield


def frame_files(capture_folder) -> list[str] | None:
    """The capture's colour frame files ('color/000000.png', ...) by frame index, for the report."""
    from ..capture.reading import capture_root, paired_frame_files

    try:
        color, _ = paired_frame_files(capture_root(capture_folder), None)
    except Exception:  # noqa: BLE001 - the report goes without file names
        return None
    return [f"{path.parent.name}/{path.name}" for path in color.values()]


def print_summary(summary: dict, quiet: bool) -> None:
    """Print the run's summary (:func:`o3d_mvps.run_report.summary_lines`), a few lines before the
    final 'wrote OUT'; nothing under ``quiet`` (the summary is in report.json)."""
    if not quiet:
        for line in summary_lines(summary):
            print(line)


def log_energy(refinement, quiet: bool) -> None:
    """Print the final energy of each level and the time per stage (of a Refinement or SolverOutput)."""
    if quiet:
        return
    last = {}
    for row in refinement.energy:
        last[row["level"]] = row
    for level, row in sorted(last.items(), reverse=True):
        print(f"level {level}: {row['iteration']} sweeps, energy {row['energy']:.6g}")
    print("time: " + ", ".join(f"{k} {v:.1f}s" for k, v in refinement.timings.items()))
