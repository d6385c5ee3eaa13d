"""All-or-nothing output folders and the small file writers shared by captures and results."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from .errors import OutputExistsError

#: How a Python caller allows replacing outputs; the command line passes "--overwrite" instead.
PYTHON_OVERWRITE = "overwrite=True"


def sibling(path: Path, tag: str) -> Path:
    """A fresh hidden name next to path, e.g. '.capture.tmp-1a2b3c4d'."""
    return path.with_name(f".{path.name}.{tag}-{uuid.uuid4().hex[:8]}")


def check_output_folder(path, overwrite: bool, *, what: str = "output folder", flag: str = PYTHON_OVERWRITE) -> Path:
    """The absolute path of an output folder, after checking that writing it replaces nothing unasked.

    Raises OutputExistsError when ``path`` is a file, or a non-empty folder and not ``overwrite``;
    ``flag`` names how the caller's user allows it (``overwrite=True`` or ``--overwrite``).
    """
    root = Path(os.path.abspath(os.path.expanduser(path)))
    if root.exists() and not root.is_dir():
        raise OutputExistsError(f"{root} is a file, not a {what}; choose another output path")
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{what} {root} already exists and is not empty; pass {flag} to replace the files this writes "
            "there (other files are kept), or choose another path"
        )
    return root


def check_output_files(paths: Iterable, overwrite: bool, *, flag: str = PYTHON_OVERWRITE) -> list[Path]:
    """The paths as Path objects; raises OutputExistsError when one exists and not ``overwrite``."""
    paths = [Path(p) for p in paths]
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} already exist(s); pass {flag} to replace, "
                                "or choose another output path")
    return paths


def move_into(new: Path, root: Path, layout: Iterable[str] = ()) -> None:
    """Move the entries of folder ``new`` into folder ``root`` (created if missing), then remove ``new``.

    Entries of ``root`` with the names of ``new``'s entries or of ``layout`` (outputs the writer
    may produce but did not this time, so a stale one cannot pass for part of the new result)
    are moved aside and deleted only once every new entry is in place; any other entry of
    ``root`` (a user's file) stays. On failure ``root`` is restored as it was.
    """
    if not root.exists():
        os.rename(new, root)
        return
    entries = sorted(p.name for p in new.iterdir())
    replaced = [n for n in sorted(set(entries) | set(layout)) if os.path.lexists(root / n)]
    old = sibling(root, "old")
    old.mkdir()
    aside, placed = [], []
    try:
        for name in replaced:
            os.rename(root / name, old / name)
            aside.append(name)
        for name in entries:
            os.rename(new / name, root / name)
            placed.append(name)
    except BaseException:
        for name in placed:
            os.rename(root / name, new / name)
        for name in aside:
            os.rename(old / name, root / name)
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
    new.rmdir()


@contextmanager
def atomic_folder(path, *, overwrite: bool = False, what: str = "output folder",
                  layout: Iterable[str] = ()) -> Iterator[Path]:
    """Write a folder all or nothing: yields an empty temporary sibling, moved into place on success.

    Refuses a file or a non-empty folder at ``path`` unless ``overwrite`` (OutputExistsError,
    see check_output_folder). With ``overwrite`` only the entries written (and those named in
    ``layout``) are replaced; other files in the folder stay (see move_into). On any exception
    the temporary folder is removed and an earlier output stays intact.
    """
    root = check_output_folder(path, overwrite, what=what)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = sibling(root, "tmp")
    tmp.mkdir()
    try:
        yield tmp
        move_into(tmp, root, layout)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_files(paths: list[Path], overwrite: bool) -> Iterator[list[Path]]:
    """Write several files all or nothing: yields temporary paths beside ``paths``, renamed into
    place once every one of them holds data; on any failure they are deleted.

    Refuses (OutputExistsError) before anything is written when a target exists and not
    ``overwrite``. Temporary names keep the target's suffix, for writers that infer the format.
    """
    paths = check_output_files(paths, overwrite)
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex[:8]
    tmps = [p.with_name(f".{p.stem}.{token}.tmp{p.suffix}") for p in paths]
    try:
        yield tmps
        for t, p in zip(tmps, paths):
            if not t.exists() or t.stat().st_size == 0:
                raise OSError(f"writing {p} produced no data")
        for t, p in zip(tmps, paths):
            os.replace(t, p)
    finally:
        for t in tmps:
            t.unlink(missing_ok=True)


def json_text(data, what: str, error=ValueError) -> str:
    """Pretty JSON of data; raises ``error`` naming ``what`` when it is not serialisable."""
    try:
        return json.dumps(data, indent=2, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise error(f"{what} is not JSON-serialisable ({e}); keep only str, number, bool, list and dict values") from None


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an (H, W), (H, W, 1), RGB (H, W, 3) or RGBA (H, W, 4) uint8/uint16 array as PNG."""
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR if image.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}; check the disk space and permissions")


def write_intrinsic_json(path: Path, K: np.ndarray, image_size: tuple[int, int]) -> None:
    """Open3D PinholeCameraIntrinsic JSON (intrinsic_matrix column-major); image_size (H, W)."""
    data = {"width": int(image_size[1]), "height": int(image_size[0]), "intrinsic_matrix": np.asarray(K).T.ravel().tolist()}
    path.write_text(json_text(data, path.name))
