"""The ``--overwrite`` option of the subcommands: outputs are checked before any work, and the
refusal names the command-line flag."""

from __future__ import annotations

from ..fileio import check_output_files, check_output_folder

OVERWRITE_FLAG = "--overwrite"


def add_overwrite_argument(parser, what: str) -> None:
    """Add ``--overwrite`` to a subcommand writing ``what`` (e.g. "output folder")."""
    parser.add_argument(OVERWRITE_FLAG, action="store_true",
                        help=f"write into an existing {what}, replacing only what this command writes there")


def check_folder(path, overwrite: bool, what: str):
    """Absolute path of the output folder; OutputExistsError (naming --overwrite) if it would replace files."""
    return check_output_folder(path, overwrite, what=what, flag=OVERWRITE_FLAG)


def check_files(paths, overwrite: bool) -> list:
    """The output paths; OutputExistsError (naming --overwrite) if one exists and not ``overwrite``."""
    return check_output_files(paths, overwrite, flag=OVERWRITE_FLAG)
