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


def json_text(data, what: str, error=ValueError) -> str:
    """Pretty JSON of data; raises ``error`` naming ``what`` when it is not serialisable."""
    try:
        return json.dumps(data, indent=2, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise error(f"{what} is not JSON-serialisable ({e}); keep only str, number, bool, list and dict values") from None


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an (H, W) or RGB (H, W, 3) uint8/uint16 array as PNG."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}; check the disk space and permissions")


def write_intrinsic_json(path: Path, K: np.ndarray, image_size: tuple[int, int]) -> None:
    """Open3D PinholeCameraIntrinsic JSON (intrinsic_matrix column-major); image_size (H, W)."""
    data = {"width": int(image_size[1]), "height": int(image_size[0]), "intrinsic_matrix": np.asarray(K).T.ravel().tolist()}
    path.write_text(json_text(data, path.name))
