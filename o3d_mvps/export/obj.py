"""Wavefront OBJ text, formatted with vectorised numpy.

Open3D 0.20's ``o3d.t.io.write_triangle_mesh`` keeps the albedo texture too, but is much
slower: 0.41 s against 0.12 s for the demo mesh (44k triangles; trimesh 0.48 s) and 45 s
against 5.6 s for a 1280x720 relief (1.8M triangles), measured on a busy 2-core machine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .topology import unique

# OBJ text is formatted with vectorised numpy (a character table per block of rows): a
# formatted Python string per record takes several times longer.
_ROWS_PER_BLOCK = 1 << 17


def write_obj(path: Path, positions: np.ndarray, tri: np.ndarray, normals: np.ndarray | None,
               uvs: np.ndarray | None, mtl_name: str | None) -> None:
    """Write a Wavefront OBJ: v (n), vt (deduplicated corner UVs), vn (n), f v/vt/vn (1-based)."""
    n = len(positions)
    corner_uv = None
    if uvs is not None:
        uv_table, corner_uv = _deduplicate_uvs(tri, uvs)
    scale = float(np.abs(positions).max(initial=1.0))
    decimals = int(np.clip(15 - np.ceil(np.log10(max(scale, 1.0))), 3, 9))
    with open(path, "wb") as fh:
        fh.write(f"# o3d_mvps mesh: {n} vertices, {len(tri)} triangles\n".encode())
        if mtl_name is not None:
            fh.write(f"mtllib {mtl_name}\nusemtl albedo\n".encode())
        _write_records(fh, b"v", [positions[:, k] for k in range(3)], decimals)
        if corner_uv is not None:
            _write_records(fh, b"vt", [uv_table[:, 0], uv_table[:, 1]], 7)
        if normals is not None:
            _write_records(fh, b"vn", [normals[:, k] for k in range(3)], 6)
        # Every index is formatted once, into a table gathered per face corner.
        n_ids = max(n, len(uv_table) if corner_uv is not None else 0)
        id_chars, id_used = _int_chars(np.arange(1, n_ids + 1))
        for start in range(0, len(tri), _ROWS_PER_BLOCK):
            block = tri[start:start + _ROWS_PER_BLOCK]
            block_uv = None if corner_uv is None else corner_uv[start:start + _ROWS_PER_BLOCK]
            pieces = [b"f"]
            for k in range(3):
                vertex = (id_chars[block[:, k]], id_used[block[:, k]])
                pieces += [b" ", vertex]
                if block_uv is not None:
                    pieces += [b"/", (id_chars[block_uv[:, k]], id_used[block_uv[:, k]])]
                if normals is not None:
                    pieces += [b"/" if block_uv is not None else b"//", vertex]
            pieces.append(b"\n")
            fh.write(_join_rows(pieces, len(block)))


def _deduplicate_uvs(tri: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique UVs (m, 2) and each corner's index (T, 3) into them.

    Fast path: when the corner UVs are a function of the vertex (meshes of
    :func:`refinement_to_mesh`), the table is per vertex and indices equal vertex indices.
    """
    uvs = np.asarray(uvs, dtype=np.float32).reshape(len(tri), 3, 2)
    per_vertex = np.zeros((int(tri.max()) + 1, 2), dtype=np.float32)
    per_vertex[tri] = uvs
    if np.array_equal(per_vertex[tri], uvs):
        return per_vertex, tri
    bits = np.ascontiguousarray(uvs.reshape(-1, 2)).view(np.uint32).astype(np.uint64)
    table_keys, inverse, _ = unique((bits[:, 0] << np.uint64(32)) | bits[:, 1])
    table = np.stack([(table_keys >> np.uint64(32)).astype(np.uint32), (table_keys & np.uint64(0xFFFFFFFF)).astype(np.uint32)], axis=1)
    return table.view(np.float32).reshape(-1, 2), inverse.reshape(len(tri), 3)


def _write_records(fh, tag: bytes, columns: list[np.ndarray], decimals: int) -> None:
    """Write lines ``tag x y ...`` of fixed-point numbers, block by block."""
    n = len(columns[0])
    for start in range(0, n, _ROWS_PER_BLOCK):
        sl = slice(start, start + _ROWS_PER_BLOCK)
        pieces = [tag]
        for col in columns:
            pieces += [b" ", _fixed_chars(np.asarray(col[sl], dtype=np.float64), decimals)]
        pieces.append(b"\n")
        fh.write(_join_rows(pieces, len(columns[0][sl])))


def _int_chars(x: np.ndarray, width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ASCII digits of non-negative integers (N,) below 1e15: right-aligned (N, width) uint8 and a used-column mask."""
    x = np.asarray(x, dtype=np.float64)  # float division is exact here and much faster than int64's
    if width is None:
        width = len(str(int(x.max(initial=0))))
    powers = 10.0 ** np.arange(width - 1, -1, -1)
    digits = np.floor(x[:, None] / powers) % 10.0 + ord("0")
    n_digits = np.maximum((x[:, None] >= powers).sum(axis=1), 1)
    used = np.arange(width) >= (width - n_digits)[:, None]
    return digits.astype(np.uint8), used


def _fixed_chars(x: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """ASCII fixed-point text ``[-]int.frac`` of floats (N,): (N, w) uint8 and a used-column mask."""
    unit = 10.0 ** decimals
    scaled = np.rint(np.abs(x) * unit)  # an exact integer in float64 (below 2**53)
    whole = np.floor(scaled / unit)
    frac = scaled - whole * unit
    w_chars, w_used = _int_chars(whole)
    f_chars, _ = _int_chars(frac, decimals)
    negative = (x < 0) & (scaled > 0)
    sign = np.where(negative, ord("-"), ord(" ")).astype(np.uint8)[:, None]
    dot = np.full((len(x), 1), ord("."), dtype=np.uint8)
    chars = np.concatenate([sign, w_chars, dot, f_chars], axis=1)
    used = np.concatenate([negative[:, None], w_used, np.ones((len(x), 1 + decimals), dtype=bool)], axis=1)
    return chars, used


def _join_rows(pieces: list, n: int) -> bytes:
    """Concatenate per-row pieces -- constant ``bytes`` or (chars, used) tables -- into n text rows."""
    chars, used = [], []
    for piece in pieces:
        if isinstance(piece, bytes):
            constant = np.frombuffer(piece, dtype=np.uint8)
            chars.append(np.broadcast_to(constant, (n, constant.size)))
            used.append(np.ones((n, constant.size), dtype=bool))
        else:
            chars.append(piece[0])
            used.append(piece[1])
    return np.concatenate(chars, axis=1)[np.concatenate(used, axis=1)].tobytes()
