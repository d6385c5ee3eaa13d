"""sRGB <-> linear RGB transfer functions (IEC 61966-2-1), float arrays in [0, 1]; colour frames kept
as their integer codes and decoded by table (:class:`CodedColours`)."""

from functools import lru_cache

import numpy as np


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear RGB, same shape, float32."""
    c = np.asarray(srgb, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Encode linear RGB in [0, 1] to sRGB values in [0, 1], same shape, float32."""
    c = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


@lru_cache(maxsize=4)
def decode_table(bits: int, srgb: bool = True) -> np.ndarray:
    """(2**bits,) float32: the value of each integer code k of a ``bits``-bit image, ``k / (2**bits - 1)``
    (in float64, as a division of the image would give), decoded by :func:`srgb_to_linear` when ``srgb``.
    Read-only (shared between calls)."""
    value = np.arange(2**bits) / float(2**bits - 1)
    table = srgb_to_linear(value) if srgb else value.astype(np.float32)
    table.flags.writeable = False
    return table


def codes_to_linear(codes: np.ndarray, srgb: bool = True) -> np.ndarray:
    """uint8 or uint16 image codes (any shape) -> float32 linear values, element for element equal to
    ``srgb_to_linear(codes / max_code)`` (or ``(codes / max_code).astype(float32)`` without ``srgb``):
    a table look-up (:func:`decode_table`), 10x cheaper than the power function on a 1280x720 frame
    (an (H, W, 3) uint8 frame through :func:`decode_frame`'s ``cv2.LUT``: 2 against 5 ms)."""
    codes = np.asarray(codes)
    if codes.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"codes_to_linear: expected uint8 or uint16 codes, got {codes.dtype}")
    table = decode_table(8 * codes.dtype.itemsize, srgb)
    if codes.dtype == np.uint8 and codes.ndim == 3 and codes.shape[2] == 3:
        return decode_frame(codes, np.broadcast_to(table, (3, table.size)))
    return table[codes]


def is_coded(frame) -> bool:
    """Whether ``frame`` is a coded colour frame: a plain tuple ``(codes, table)`` of
    :meth:`CodedColours.frame` (a float (H, W, 3) array is not)."""
    return isinstance(frame, tuple)


def decode_frame(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: channel c of each pixel is ``table[c, codes[..., c]]`` (codes (H, W, 3)
    uint8/uint16, table (3, K) float32, K = 2**bits). The one place codes become floats; 8-bit
    codes through ``cv2.LUT`` (2 ms a 1280x720 frame against 8 ms for NumPy's gathers)."""
    if codes.dtype == np.uint8:
        import cv2

        return cv2.LUT(codes, np.ascontiguousarray(table.T[None]))  # a (1, 256, 3) per-channel table
    out = np.empty(codes.shape, dtype=np.float32)
    for c in range(3):
        out[..., c] = table[c][codes[..., c]]
    return out


def float_frame(frame) -> np.ndarray:
    """A colour frame as (H, W, 3) float32 linear RGB: a coded frame ``(codes, table)``
    (:func:`is_coded`) decoded by :func:`decode_frame`, a float array itself."""
    return decode_frame(*frame) if is_coded(frame) else frame


def frames_and_tables(frames: list) -> tuple[tuple, tuple | None]:
    """Colour frames as one launch of the solver's kernels takes them: (a tuple of the float
    frames, None), or of coded frames (a tuple of their codes, a tuple of their tables)
    (:func:`o3d_mvps.solver.kernels.frame_at`)."""
    if frames and is_coded(frames[0]):
        return tuple(f[0] for f in frames), tuple(f[1] for f in frames)
    return tuple(frames), None


class CodedColours:
    """n colour frames kept as the integer codes they were stored with, and per frame a table of
    each code's linear value per channel (any white balance or gain the frame is divided by folded
    in): 1 byte a channel for 8-bit files instead of 4 as float32 (20 frames of 1280x720: 55 MB
    against 221 MB).

    codes: n (H, W, 3) uint8 or uint16 arrays (not copied: a capture's own frames), one dtype.
    tables: (n, 3, K) float32, K = 2**bits: frame i's channel c value of code k is
    ``tables[i, c, k]``.

    Indexing gives a frame decoded to (H, W, 3) float32 (a new array each time,
    :func:`decode_frame`), so code that reads a list of float frames reads these unchanged;
    :meth:`frame` gives the kernels' form, a plain tuple ``(codes, table)``, which the solver's
    sampling kernels decode per sample (:func:`o3d_mvps.solver.kernels.frame_value`): the same
    floats, so the same results bit for bit as the decoded frames'.
    """

    def __init__(self, codes, tables):
        self.codes = [np.ascontiguousarray(c) for c in codes]
        self.tables = np.ascontiguousarray(tables, dtype=np.float32)
        n = len(self.codes)
        dtype = self.codes[0].dtype if n else np.dtype(np.uint8)
        if dtype not in (np.uint8, np.uint16) or any(c.dtype != dtype for c in self.codes):
            raise ValueError(f"CodedColours: codes must all be uint8 or all uint16, got "
                             f"{sorted({str(c.dtype) for c in self.codes})}")
        if self.tables.shape != (n, 3, 2 ** (8 * dtype.itemsize)):
            raise ValueError(f"CodedColours: tables must be (n, 3, K) = {(n, 3, 2 ** (8 * dtype.itemsize))} for "
                             f"{n} {dtype} frames, got {self.tables.shape}")

    @classmethod
    def from_codes(cls, codes, srgb: bool = True) -> "CodedColours":
        """Frames of ``codes`` (n (H, W, 3) uint8/uint16 arrays) decoded as the files' encoding
        says (:func:`decode_table`), every frame and channel alike."""
        codes = list(codes)
        bits = 8 * np.asarray(codes[0]).dtype.itemsize if codes else 8
        table = decode_table(bits, srgb)
        return cls(codes, np.broadcast_to(table, (len(codes), 3, table.size)))

    def divided(self, factors: np.ndarray) -> "CodedColours":
        """These frames with frame i's channel c divided by ``factors[i, c]`` ((n, 3)), as a float32
        frame divided by ``factors[i].astype(float32)`` would be (the tables divided; codes shared)."""
        factors = np.asarray(factors).astype(np.float32)
        return CodedColours(self.codes, (self.tables / factors[:, :, None]).astype(np.float32))

    def frame(self, i: int) -> tuple:
        """Frame i as the kernels read it: ``(codes (H, W, 3), table (3, K))``, both shared."""
        return self.codes[i], self.tables[i]

    @property
    def shape(self) -> tuple:
        """(n, H, W, 3)."""
        return (len(self.codes), *self.codes[0].shape) if self.codes else (0, 0, 0, 3)

    @property
    def nbytes(self) -> int:
        return sum(c.nbytes for c in self.codes) + self.tables.nbytes

    def __len__(self) -> int:
        return len(self.codes)

    def __getitem__(self, i: int) -> np.ndarray:
        return decode_frame(*self.frame(i))

    def __iter__(self):
        return (self[i] for i in range(len(self)))
