"""The ``--overwrite`` option of the subcommands (outputs are checked before any work, and the
refusal names the command-line flag) and the solver's log of what it did."""

from __future__ import annotations

from ..fileio import check_output_files, check_output_folder

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
