"""glibc's malloc settings for the solver's large arrays (Linux): which freed blocks go back to
the system at once, which stay in the heap to be reused, and the heap's free pages given back
between stages. Process-wide; the functions that set it are no-ops returning False elsewhere,
and settings the user's process started with are kept."""

from __future__ import annotations

import ctypes
import os
import sys

#: glibc's M_MMAP_THRESHOLD (bytes) that :func:`return_freed_arrays` sets for a static camera's
#: frames of at least :data:`MMAP_MIN_PIXELS` colour pixels (or no size given), and for a moving
#: camera's frames of any size
MMAP_THRESHOLD = 1 << 20
MOVING_MMAP_THRESHOLD = 8 << 20
#: D415 x 20 (0.92 M pixels), whole process: peak 938 MB at 1 MB and at 8 MB, 962 MB with glibc's
#: default; system CPU 4.4, 2.1 and 1.7 s of ~24 s (1.03 M, 0.22 M, 0.17 M page faults). At 2 MP
#: (1.94 M) 1 MB had lowered the stage peaks by 50-190 MB, while each joint-step block and lighting
#: frame took fresh arrays; with those reused (docs/performance.md, "2 MP: fresh pages"), 8 MB
#: took the 2 MP x 20 solve's system CPU from 24.5 to 19.6 s (3.8 M to 1.6 M page faults) for a
#: peak 60 MiB higher (2632 -> 2692 MiB, saved problem; the whole command 2827-2925 -> 2877 MiB,
#: within its run-to-run spread)
MMAP_MIN_PIXELS = 1_500_000
#: ... and for a static camera's frames under :data:`MMAP_MIN_PIXELS` (poses held at the identity):
#: glibc's own ceiling. The 1280x960 quilt (20 frames, one numba thread): system CPU 8.4 s at 8 MB
#: (its CG and AMG vectors of 1.13 M float64, 9 MB, each mapped and faulted in anew), 7.1 s at
#: 16 MB, 6.0 s at 32 MB; process peak 3.03, 3.07, 3.05 GB.
STATIC_MMAP_THRESHOLD = 32 << 20
#: These thresholds hold where the heap-only mode is not taken (:func:`heap_only`; the user's
#: settings). For a static camera's frames of any size that mode maps no block at all
#: (``M_MMAP_MAX`` 0) and keeps the heap's top (``M_TRIM_THRESHOLD`` at
#: :data:`KEPT_TRIM_THRESHOLD`). Before it, the frames x pixels arrays (272 MB a float32 (20, 1.13
#: M, 3)) that each sweep makes and frees were mapped anew each time, and each of their pages
#: zeroed by the kernel at its first touch (the 1280x960 quilt, two numba threads, this mode off
#: and on in alternation: system CPU 9.1, 9.5 -> 6.5, 7.0 s, refine 29.2, 30.5 -> 27.4, 27.8 s,
#: process peak 3.03-3.09 -> 3.29 GB). The solve sets glibc's defaults back when it ends
#: (:func:`map_large_blocks`). At D415 size (moving camera) the same halved the system CPU (2.1-2.8
#: -> 1.2 s) but not the refine's wall time, for 30-50 MB more: not done there
#: (docs/performance.md, "A static camera's arrays kept in the heap"). A static camera's larger
#: frames take it too: a 1600x1200 static quilt (20 frames), two pairs, refine 60.7, 59.6 -> 47.6,
#: 50.1 s, system CPU 24.4, 23.9 -> 11.1, 11.9 s, the same results, process peak 4.27 -> 4.71-4.74
#: GiB (docs/performance.md, "Every block from the heap at 2 MP")
STATIC_HEAP_ONLY = True
#: ... and the same for a moving camera's frames of :data:`MMAP_MIN_PIXELS` colour pixels and more,
#: registration included: the 2 MP render ``mp2s2`` (1708x1136, 20 frames, two numba threads)
#: spent 16-18 of its 97-108 CPU s in the kernel, its frames x pixels arrays (77 MB a float32
#: (20, 958 000), 230 MB with 3 channels) mapped and zeroed anew each sweep. Three alternating
#: pairs: refine 77.5, 66.4, 69.0 -> 64.9, 55.7, 58.2 s, system CPU 5.2-5.4 s, the same results,
#: process peak +160-265 MiB (2.42-2.61 GiB; docs/performance.md, "Every block from the heap at 2 MP")
MOVING_HEAP_ONLY = True
KEPT_TRIM_THRESHOLD = (1 << 31) - 1  # mallopt's int: 2 GB
#: glibc's M_MMAP_MAX default, set back by :func:`map_large_blocks`
DEFAULT_MMAP_MAX = 65536
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_MMAP_MAX = -1, -3, -4
#: the mmap threshold :func:`return_freed_arrays` set last where it also made every block come
#: from the heap (None: it did not), for :func:`map_large_blocks`
_heap_only: list[int | None] = [None]


def _user_malloc_settings() -> set:
    """glibc's malloc parameters that this process's environment set when it started ("mmap_threshold",
    "mmap_max", "trim_threshold": ``MALLOC_MMAP_THRESHOLD_``, ... or their ``glibc.malloc``
    tunables): the user's, which :func:`return_freed_arrays` keeps. Read from /proc/self/environ,
    the environment glibc read: a variable set later (Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_``
    in its own process for the workers it spawns) did not reach this process's malloc."""
    try:
        with open("/proc/self/environ", "rb") as f:
            entries = [entry.decode(errors="replace") for entry in f.read().split(b"\0") if entry]
        environ = dict(entry.split("=", 1) for entry in entries if "=" in entry)
    except OSError:
        environ = dict(os.environ)
    tunables = environ.get("GLIBC_TUNABLES", "")
    return {name for name in ("mmap_threshold", "mmap_max", "trim_threshold")
            if f"MALLOC_{name.upper()}_" in environ or f"glibc.malloc.{name}=" in tunables}


def _libc_function(name: str):
    """glibc's ``name`` (ctypes), or None where the C library is not glibc on Linux."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return getattr(ctypes.CDLL("libc.so.6"), name)
    except (OSError, AttributeError):
        return None


def heap_only(pixels: int | None, static: bool) -> bool:
    """Whether :func:`return_freed_arrays` takes every block from the heap for frames of
    ``pixels`` colour pixels (None: no size given, never): a static camera's of any size
    (:data:`STATIC_HEAP_ONLY`), a moving camera's from :data:`MMAP_MIN_PIXELS` on
    (:data:`MOVING_HEAP_ONLY`)."""
    if pixels is None:
        return False
    if static:
        return STATIC_HEAP_ONLY
    return MOVING_HEAP_ONLY and pixels >= MMAP_MIN_PIXELS


def return_freed_arrays(pixels: int | None = None, static: bool = False) -> bool:
    """Have glibc's malloc give every block of at least 8 MB (:data:`MOVING_MMAP_THRESHOLD`,
    a moving camera's frames; for a static camera's, ``static``: 1 MB, :data:`MMAP_THRESHOLD`,
    from :data:`MMAP_MIN_PIXELS` colour pixels on or with no size ``pixels`` given, 32 MB,
    :data:`STATIC_MMAP_THRESHOLD`, under that size) its own mapping, returned to the system when
    freed (``mallopt(M_MMAP_THRESHOLD)``, process-wide). Where :func:`heap_only` says so (a static
    camera's frames of any size, a moving camera's from 1.5 megapixels on) take every block from
    the heap instead and keep the heap's top: freed blocks are reused, not faulted in and zeroed
    anew, until :func:`map_large_blocks` (the solve's end; a call that does not choose it ends it
    too).

    By default glibc raises that threshold up to 32 MB as large blocks are freed, and the
    solver's per-level arrays of 1-32 MB then stay in the heap when freed, resident and
    fragmented: 24 MB of the D415 process's peak, 50-190 MB of the stage peaks at 2 MP. Each
    mapped array costs page faults when it is allocated: at D415 size the 1 MB threshold cost
    2.7 s of system CPU, 8 MB 0.4 s, for the same peak. A block that fits free space already
    in the heap is still carved from it, so call this before the large work. A no-op returning
    False where the C library is not glibc, or where the user set glibc's mmap threshold when the
    process started (:func:`_user_malloc_settings`; the heap-only mode, likewise, where they set
    its mmap count or trim threshold: Dask's workers)."""
    mallopt = _libc_function("mallopt")
    users = _user_malloc_settings()
    if mallopt is None or "mmap_threshold" in users:
        return False
    if static:
        threshold = STATIC_MMAP_THRESHOLD if pixels is not None and pixels < MMAP_MIN_PIXELS else MMAP_THRESHOLD
    else:
        threshold = MOVING_MMAP_THRESHOLD
    done = bool(mallopt(M_MMAP_THRESHOLD, threshold))
    if heap_only(pixels, static) and not users & {"mmap_max", "trim_threshold"}:
        _heap_only[0] = threshold
        return done and bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, KEPT_TRIM_THRESHOLD))
    if _heap_only[0] is not None:
        _heap_only[0] = threshold  # the trim threshold set back is the one paired with this threshold
    return map_large_blocks() and done


def map_large_blocks() -> bool:
    """End :func:`return_freed_arrays`' heap-only mode, where it is on: blocks over the mmap
    threshold mapped again (glibc's ``M_MMAP_MAX``) and the heap's top returned from the trim
    threshold glibc's dynamic rule pairs with that mmap threshold (twice it). True where nothing
    was to be done; False where the C library is not glibc."""
    mallopt = _libc_function("mallopt")
    if mallopt is None:
        return False
    threshold, _heap_only[0] = _heap_only[0], None
    if threshold is None:
        return True
    return bool(mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)) and bool(mallopt(M_TRIM_THRESHOLD, 2 * threshold))


def trim_heap() -> bool:
    """Give the freed pages inside glibc's heap back to the system (``malloc_trim(0)``), where
    the blocks below the mmap threshold (:func:`return_freed_arrays`) that a stage freed lie
    between blocks still in use, so that they stop counting in the resident set. A no-op
    returning False where the C library is not glibc. Called as each pyramid level starts,
    when the previous level's arrays are gone, once the last level is solved, and by
    :func:`o3d_mvps.solving.refine` once the solver's input is gone; the values computed do not
    change."""
    malloc_trim = _libc_function("malloc_trim")
    return malloc_trim is not None and bool(malloc_trim(0))
