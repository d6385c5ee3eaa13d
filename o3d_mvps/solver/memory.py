"""The process's resident set: library pages mapped but not run released between stages.

:func:`release_library_pages` (Linux) unmaps the clean pages of shared libraries' file mappings;
the solver's heap is :func:`o3d_mvps.solver.driver.trim_heap`'s and
:func:`o3d_mvps.solver.driver.return_freed_arrays`' (glibc).
"""

from __future__ import annotations

#: madvise(2)'s MADV_DONTNEED (Linux)
MADV_DONTNEED = 4


def release_library_pages() -> float:
    """Unmap the pages of the process's private read-only file mappings (shared libraries' code
    and constants) that hold no anonymous page, with ``madvise(MADV_DONTNEED)``; the MiB released
    from the resident set. 0.0 where the system is not Linux (or has no libc ``madvise``).

    Loading Open3D, llvmlite (numba) and OpenCV makes about 230 MiB of their files resident
    (their static initialisers run all over the files, and the kernel maps file pages around each
    fault, in large pieces on this machine's Linux 6.18); most of it does not run again: in the
    D415 command (1280x720, 20 frames) 321 of the 1061 MiB resident at the solve's peak were file
    pages, about 50 of 770 MiB with the calls as :func:`o3d_mvps.solving.refine` starts, as
    :func:`o3d_mvps.solver.driver.solve` starts its finest level and in
    :func:`o3d_mvps.report_page.mesh_viewer_html` (after the VTK import). A
    page dropped here that is read again is mapped again from the page cache (a minor fault: the
    solve's kernels take back 50-90 MiB of llvmlite a pyramid level as they load); one never read
    again stops counting. Mappings with anonymous pages (a library's relocated data, made
    read-only after loading: copy-on-write pages that the file does not hold) are left alone, so
    no value in memory changes. About 30 ms of CPU a call (reading ``/proc/self/smaps``). Call it
    between stages, from the thread that loads libraries (the mappings are read first, then
    advised)."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return 0.0
    try:
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return 0.0
    madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    released_kb = 0
    for start, end, resident_kb in _clean_file_mappings():
        if madvise(start, end - start, MADV_DONTNEED) == 0:
            released_kb += resident_kb
    return released_kb / 1024.0


def _clean_file_mappings() -> list[tuple[int, int, int]]:
    """(start, end, resident kB) of each mapping in ``/proc/self/smaps`` that is a private,
    read-only mapping of a file with resident pages and no anonymous (copy-on-write) page."""
    found, current = [], None
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            field = line.split(None, 6)
            if not field[0].endswith(":"):  # a mapping's header: range perms offset dev inode [path]
                start, end = (int(x, 16) for x in field[0].split("-"))
                path = field[5].strip() if len(field) > 5 else ""
                current = {"range": (start, end), "file": field[1][1] == "-" and field[1][3] == "p"
                           and path.startswith("/"), "rss": 0, "anon": 0}
                found.append(current)
            elif field[0] == "Rss:":
                current["rss"] = int(field[1])
            elif field[0] == "Anonymous:":
                current["anon"] = int(field[1])
    return [(*m["range"], m["rss"]) for m in found if m["file"] and m["rss"] > 0 and m["anon"] == 0]
