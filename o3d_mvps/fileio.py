"""All-or-nothing output folders and the small file writers shared by captures and results."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from .errors import OutputExistsError


def sibling(path: Path, tag: str) -> Path:
    """A fresh hidden name next to path, e.g. '.capture.tmp-1a2b3c4d'."""
    return path.with_name(f".{path.name}.{tag}-{uuid.uuid4().hex[:8]}")


def swap_into_place(new: Path, path: Path) -> None:
    """Rename folder new to path; an existing path is moved aside and deleted only after success."""
    if not path.exists():
        os.rename(new, path)
        return
    old = sibling(path, "old")
    os.rename(path, old)
    try:
        os.rename(new, path)
    except BaseException:
        os.rename(old, path)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_folder(path, *, overwrite: bool = False, what: str = "output folder") -> Iterator[Path]:
    """Write a folder all or nothing: yields an empty temporary sibling, renamed into place on success.

    Refuses a file or a non-empty folder at ``path`` unless ``overwrite`` (OutputExistsError);
    on any exception the temporary folder is removed and an earlier output stays intact.
    """
    root = Path(os.path.abspath(os.path.expanduser(path)))
    if root.exists() and not root.is_dir():
        raise OutputExistsError(f"{root} is a file, not a {what}; choose another output path")
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{what} {root} already exists and is not empty; pass overwrite=True (--overwrite) "
            "to replace it, or choose another path"
        )
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = sibling(root, "tmp")
    tmp.mkdir()
    try:
        yield tmp
        swap_into_place(tmp, root)
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
    paths = [Path(p) for p in paths]
    if not overwrite:
        existing = [str(p) for p in paths if p.exists()]
        if existing:
            raise OutputExistsError(f"{', '.join(existing)} already exist(s); pass overwrite=True "
                                    "(--overwrite) to replace, or choose another output path")
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
