"""All-or-nothing outputs, checked before the work, and the small file writers shared by captures and results.

Every output is checked before any long work (:func:`check_output_folder`,
:func:`check_output_files`): a file or folder that would be replaced unasked, a parent that is a
file, a folder that cannot be written (read-only, no permission), an output inside an input
folder (a capture changed by its own refinement), a folder where a file is wanted, and a disk
with almost no free space. Results are written into a hidden staging folder on the target's own
file system -- inside the output folder when it exists (it may be a mount point), else beside
it -- and renamed into place, so an output on another disk works and a failure leaves no part.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from .errors import OutputExistsError, OutputPathError

#: How a Python caller allows replacing outputs; the command line passes "--overwrite" instead.
PYTHON_OVERWRITE = "overwrite=True"
#: Least free space (bytes) on the output's disk for a command to start.
MIN_FREE_BYTES = 16 * 2**20
#: Prefix of the hidden staging folders and files (``.o3d_mvps.tmp-1a2b3c4d``).
STAGING = ".o3d_mvps"


def sibling(path: Path, tag: str) -> Path:
    """A fresh hidden name next to path, e.g. '.capture.tmp-1a2b3c4d'."""
    return path.with_name(f".{path.name}.{tag}-{uuid.uuid4().hex[:8]}")


def _absolute(path) -> Path:
    return Path(os.path.abspath(os.path.expanduser(path)))


def existing_folder(path: Path) -> Path:
    """The nearest existing folder at or above ``path`` (absolute); OutputPathError naming the
    file when an ancestor of ``path`` is a file (the output cannot be created inside it)."""
    for parent in [path, *path.parents]:
        if parent.is_dir():
            return parent
        if parent.exists() or parent.is_symlink():
            if parent != path:
                raise OutputPathError(f"cannot create {path}: {parent} is a file, not a folder; choose an output "
                                      "path whose parent folders are folders")
    return Path(path.anchor)


def full_disk_message(path: Path) -> str:
    free = shutil.disk_usage(existing_folder(path)).free
    return (f"the disk holding {path} is full ({free / 2**20:.1f} MB free, ENOSPC: no space left on device); "
            "free some space or choose an output on another disk")


def check_writable(folder: Path, target: Path) -> None:
    """OutputPathError when no file can be created in the existing ``folder`` (read-only, no
    permission) or its disk has less than :data:`MIN_FREE_BYTES` free; ``target`` is named."""
    probe = folder / f"{STAGING}.probe-{uuid.uuid4().hex[:8]}"
    try:
        probe.mkdir()
        probe.rmdir()
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise OutputPathError(full_disk_message(target)) from None
        raise OutputPathError(f"cannot write {target}: {folder} is not writable ({e.strerror}); choose an output "
                              "folder you can write to, or change its permissions") from None
    if shutil.disk_usage(folder).free < MIN_FREE_BYTES:
        raise OutputPathError(full_disk_message(target))


def check_outside_inputs(path: Path, inputs: Iterable, what: str) -> None:
    """OutputPathError when ``path`` is one of the ``inputs`` folders or files, or lies inside one
    (a refinement written into its capture changes the capture's next run)."""
    real = Path(os.path.realpath(path))
    for given in inputs:
        if given is None:
            continue
        source = Path(os.path.realpath(_absolute(given)))
        if real == source or (source.is_dir() and source in real.parents):
            where = "is" if real == source else "is inside"
            raise OutputPathError(f"{what} {path} {where} the input {source}: writing there would change the input "
                                  "(and its next run); choose an output path outside it")


def check_output_folder(path, overwrite: bool, *, what: str = "output folder", flag: str = PYTHON_OVERWRITE,
                        inputs: Iterable = ()) -> Path:
    """The absolute path of an output folder, after checking that it can be written and that
    writing it replaces nothing unasked.

    Raises OutputExistsError when ``path`` is a file, or a non-empty folder and not ``overwrite``;
    ``flag`` names how the caller's user allows it (``overwrite=True`` or ``--overwrite``).
    Raises OutputPathError when a parent is a file, the folder (or the nearest existing parent)
    cannot be written or its disk is full, or ``path`` is or lies inside one of ``inputs``.
    """
    root = _absolute(path)
    if root.exists() and not root.is_dir():
        raise OutputExistsError(f"{root} is a file, not a {what}; choose another output path")
    check_outside_inputs(root, inputs, what)
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{what} {root} already exists and is not empty; pass {flag} to replace the files this writes "
            "there (other files are kept), or choose another path"
        )
    check_writable(existing_folder(root), root)
    return root


def check_output_files(paths: Iterable, overwrite: bool, *, flag: str = PYTHON_OVERWRITE,
                       inputs: Iterable = ()) -> list[Path]:
    """The paths as Path objects, after the checks of :func:`check_output_folder` for files:
    OutputExistsError when one exists and not ``overwrite``; OutputPathError when one is a
    folder, lies in a file, or is one of ``inputs``, or its folder cannot be written."""
    paths = [Path(p) for p in paths]
    for p in paths:
        if p.is_dir():
            example = p / ("output" + (p.suffix or ".npz"))
            raise OutputPathError(f"{p} is a folder; name the file to write, e.g. {example}")
        check_outside_inputs(_absolute(p), inputs, "output file")
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} already exist(s); pass {flag} to replace, "
                                "or choose another output path")
    for p in paths:
        check_writable(existing_folder(_absolute(p).parent), p)
    return paths


@contextmanager
def _named_failures(target: Path) -> Iterator[None]:
    """Turn a full disk met while writing ``target`` into OutputPathError saying so."""
    try:
        yield
    except OSError as e:
        full = e.errno == errno.ENOSPC or (e.errno is None and shutil.disk_usage(existing_folder(target)).free
                                           < 2**20)
        if full:
            raise OutputPathError(full_disk_message(target)) from e
        raise


def move_into(new: Path, root: Path, layout: Iterable[str] = ()) -> None:
    """Move the entries of folder ``new`` into folder ``root`` (created if missing), then remove ``new``.

    Entries of ``root`` with the names of ``new``'s entries or of ``layout`` (outputs the writer
    may produce but did not this time, so a stale one cannot pass for part of the new result)
    are moved aside (into a hidden folder inside ``root``: the same file system) and deleted
    only once every new entry is in place; any other entry of ``root`` (a user's file) stays.
    On failure ``root`` is restored as it was.
    """
    if not root.exists():
        os.rename(new, root)
        return
    entries = sorted(p.name for p in new.iterdir())
    replaced = [n for n in sorted(set(entries) | set(layout)) if os.path.lexists(root / n)]
    old = root / f"{STAGING}.old-{uuid.uuid4().hex[:8]}"
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


def staging_folder(root: Path) -> Path:
    """Where a folder output is staged: a hidden folder inside ``root`` when it exists (so the
    final renames stay on its file system, even when ``root`` is a mount point), else beside it."""
    if root.is_dir():
        return root / f"{STAGING}.tmp-{uuid.uuid4().hex[:8]}"
    return sibling(root, "tmp")


@contextmanager
def atomic_folder(path, *, overwrite: bool = False, what: str = "output folder",
                  layout: Iterable[str] = ()) -> Iterator[Path]:
    """Write a folder all or nothing: yields an empty staging folder, moved into place on success.

    Refuses a file or a non-empty folder at ``path`` unless ``overwrite`` (OutputExistsError,
    see check_output_folder). With ``overwrite`` only the entries written (and those named in
    ``layout``) are replaced; other files in the folder stay (see move_into). On any exception
    the staging folder is removed and an earlier output stays intact; a full disk raises
    OutputPathError saying so.
    """
    root = check_output_folder(path, overwrite, what=what)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = staging_folder(root)
    tmp.mkdir()
    try:
        with _named_failures(root):
            yield tmp
            move_into(tmp, root, layout)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_files(paths: list[Path], overwrite: bool) -> Iterator[list[Path]]:
    """Write several files all or nothing: yields temporary paths beside ``paths`` (same folder,
    so same file system), renamed into place once every one of them holds data; on any failure
    they are deleted.

    Refuses (OutputExistsError, OutputPathError) before anything is written when a target exists
    and not ``overwrite``, or cannot be written (:func:`check_output_files`). Temporary names keep
    the target's suffix, for writers that infer the format.
    """
    paths = check_output_files(paths, overwrite)
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex[:8]
    tmps = [p.with_name(f".{p.stem}.{token}.tmp{p.suffix}") for p in paths]
    try:
        with _named_failures(paths[0]):
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
