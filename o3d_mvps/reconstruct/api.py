"""``reconstruct(capture) -> Reconstruction``: refine reference views around the object, fuse one mesh.

Steps: poses (given, else the registration chain); ``references`` reference views with
spread-out viewing directions; for each, the frames that see its surface
(:func:`o3d_mvps.covisibility.frames_seeing_reference`) and a refinement with the poses re-based onto
it, as Dask tasks (:mod:`.parallel`); the refined depths fused with per-pixel weights
(:mod:`.fusion`); the mesh's largest piece kept, small holes closed (:mod:`.surface`), vertices
coloured from the refined albedos (:mod:`.colour`) and one UV atlas texture baked from them
(:mod:`.texture`). :meth:`Reconstruction.printable_solid` closes it for
printing (:mod:`.solid`). World frame: the capture's frame-0 camera, metres.
"""

from __future__ import annotations

import time
import warnings
from contextlib import ExitStack
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d

from ..errors import MVPSError
from ..run_report import peak_memory_mb, workers_peak_memory_mb
from ..solver.device import check_device_name
from ..solver.options import RefineOptions
from ..covisibility import MIN_COVISIBILITY, MIN_WELL_COVISIBLE, MOST_OF_REFERENCE, WEAK_COVERAGE_NOTE
from .fusion import GRAZING_EXPONENT, TSDFVolume, pixel_weights
from .references import FULL_TURN_DEG, azimuth_span_deg, choose_references, up_direction
from .solid import closed_solid
from .colour import ViewColours
from .surface import clean_mesh
from .texture import texture_mesh
from .views import DEPTH_SOURCES, plan_view, run_view


@dataclass
class ReconstructOptions:
    """Options of :func:`reconstruct`.

    references: reference views refined and fused. frames_per_reference: most frames refined
    with a reference besides it (those seeing most of its surface). min_covisibility: least
    fraction of a reference's surface a frame must see. depth: "refined" or "raw" (the sensor
    depth bicubic-upsampled, for comparison). voxel_mm: TSDF voxel edge. edge_px: width of the
    silhouette ramp of the fusion weights. weight_threshold: least accumulated weight of a
    fused surface voxel. hole_mm: largest hole closed in the mesh. texture_px: edge of the
    square albedo texture (0: vertex colours only). refine: the solver's
    options. workers: local Dask worker processes (default: the CPU count), >= 1.
    scheduler_timeout: seconds to wait for a scheduler to answer or, while it has no worker,
    for one (then the views fail, naming the address). progress: bars and Dask's notices
    (False: Dask logs errors only). device: where each view is refined, "auto" (the GPU when it
    can solve, else the CPU), "cpu" or "cuda:N" (:func:`o3d_mvps.solver.device.check_device`).
    """

    references: int = 8
    frames_per_reference: int = 8
    min_covisibility: float = MIN_COVISIBILITY
    depth: str = "refined"
    voxel_mm: float = 1.5
    edge_px: float = 3.0
    weight_threshold: float = 0.5
    hole_mm: float = 15.0
    texture_px: int = 1024
    refine: RefineOptions = field(default_factory=lambda: RefineOptions(progress=False))
    workers: int | None = None
    scheduler_timeout: float = 60.0
    progress: bool = True
    device: str = "auto"

    def __post_init__(self):
        check_device_name(self.device)
        if self.depth not in DEPTH_SOURCES:
            raise ValueError(f"depth={self.depth!r}; choose one of {', '.join(DEPTH_SOURCES)}")
        for name in ("voxel_mm", "edge_px", "weight_threshold", "hole_mm", "scheduler_timeout"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value!r} must be a positive number")
        if not (isinstance(self.references, int) and self.references >= 1):
            raise ValueError(f"references={self.references!r} must be an integer >= 1")
        if not (isinstance(self.frames_per_reference, int) and self.frames_per_reference >= 2):
            raise ValueError(f"frames_per_reference={self.frames_per_reference!r} must be an integer >= 2")
        if not (isinstance(self.texture_px, int) and self.texture_px >= 0):
            raise ValueError(f"texture_px={self.texture_px!r} must be an integer >= 0 (0: no texture)")
        if not (self.workers is None or (isinstance(self.workers, int) and self.workers >= 1)):
            raise ValueError(f"workers={self.workers!r} must be an integer >= 1, or None for the CPU count")


@dataclass
class Reconstruction:
    """The fused mesh and how it was made.

    mesh: o3d.t TriangleMesh, metres in the capture's frame-0 camera, vertex normals, sRGB
    vertex colours and (unless ``texture_px=0`` or the atlas failed) ``triangle.texture_uvs``
    with an sRGB albedo texture in its material. views: the reference views fused (:class:`~.views.ViewResult`).
    failed: {reference: error} of views that failed. goes_around: whether the frames cover
    the object all round (else the back is missing). azimuth_span_deg: degrees covered.
    up: (3,) the capture's up axis. info: settings, selections, timings (JSON-ready).
    """

    mesh: o3d.t.geometry.TriangleMesh
    views: list
    failed: dict
    goes_around: bool
    azimuth_span_deg: float
    up: np.ndarray
    voxel: float
    info: dict

    def printable_solid(self, size_mm: float = 100.0) -> o3d.t.geometry.TriangleMesh:
        """A closed solid of the object in millimetres (largest extent ``size_mm``, +z up), carved
        from the views' depths; what no view saw (the bottom; the back of an arc) is closed flat."""
        positions = self.mesh.vertex.positions.numpy().astype(np.float64)
        return closed_solid(self.views, positions, self.up, self.voxel, size_mm)


def reconstruct(capture, options: ReconstructOptions | None = None, *, poses=None, client=None,
                scheduler: str | None = None) -> Reconstruction:
    """Reconstruct the whole object of a capture that goes around it (module docstring).

    Parameters
    ----------
    capture : Capture
        Frames around the object; frame 0 defines the world frame.
    options : ReconstructOptions
    poses : (n, 4, 4) array, optional
        Frame 0 -> frame i (e.g. :func:`o3d_mvps.capture.read_capture_poses`); default: the
        registration chain (frames it cannot place are dropped with a warning).
    client : dask.distributed.Client, optional
        Where the refinements run; ``scheduler`` (``tcp://HOST:PORT``) connects to one;
        default: a local cluster of ``options.workers`` single-threaded processes.

    Raises
    ------
    MVPSError
        Every reference view failed (each failure is named), or the fused mesh is empty.
    """
    options = options or ReconstructOptions()
    with ExitStack() as dask_session:
        return _reconstruct(capture, options, poses, client, scheduler, dask_session)


def _reconstruct(capture, options: ReconstructOptions, poses, client, scheduler, dask_session: ExitStack):
    """:func:`reconstruct`; a user's scheduler is connected to first (a wrong address fails in
    seconds, not after the registration), a local cluster only when the views are planned."""
    from .parallel import dask_client, run_views

    t0 = time.perf_counter()
    dask_args = dict(timeout=options.scheduler_timeout, quiet=not options.progress)
    dask = None
    if options.depth == "refined" and (client is not None or scheduler is not None):
        dask = dask_session.enter_context(dask_client(client, scheduler, **dask_args))
    n_given, kept, dropped = capture.n_frames, list(range(capture.n_frames)), {}
    poses_given = poses is not None
    if poses is None:
        from ..odometry import register_frames

        registration = register_frames(capture, progress=options.progress)
        kept, dropped = list(registration.frames), registration.dropped
        capture, poses = replace(capture.select(registration.frames), frame_ids=[
            capture.frame_id(i) for i in registration.frames]), registration.poses  # named as given
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (capture.n_frames, 4, 4):
        raise ValueError(f"poses must be ({capture.n_frames}, 4, 4) for the capture's frames, got {poses.shape}")
    span = azimuth_span_deg(poses)
    goes_around = span >= FULL_TURN_DEG
    if not goes_around:
        warnings.warn(f"the frames cover {span:.0f} degrees around the object: the mesh holds what they saw, the "
                      "back is missing (walk all round the object for a closed mesh)", stacklevel=3)
    references = choose_references(poses, min(options.references, capture.n_frames))
    jobs = [plan_view(capture, poses, k, min_covisibility=options.min_covisibility,
                      max_frames=options.frames_per_reference, poses_given=poses_given) for k in references]
    refine_options = replace(options.refine, frames=None, progress=False)
    t_plan = time.perf_counter()
    memory = {"plan": peak_memory_mb()}
    retried = {}
    if options.depth == "refined":
        if dask is None:
            dask = dask_session.enter_context(
                dask_client(None, None, options.workers or min(len(jobs), _cpu_count()), **dask_args))
        views, failed, retried = run_views(jobs, refine_options, "refined", dask, options.progress,
                                           timeout=options.scheduler_timeout, device=options.device)
        dask_session.close()  # the local cluster's processes are not kept through the fusion
    else:
        views, failed = [run_view(job, refine_options, "raw") for job in jobs], {}
    for reference, why in retried.items():
        warnings.warn(why if isinstance(reference, str) else f"reference view {reference} was run again: {why}",
                      stacklevel=3)
    for message in view_warnings(views):
        warnings.warn(message, stacklevel=3)
    for reference, error in failed.items():
        warnings.warn(f"reference view {reference} failed and is left out: {error}", stacklevel=3)
    if not views:
        raise MVPSError("every reference view failed: " + "; ".join(f"{k}: {e}" for k, e in failed.items()))
    t_views = time.perf_counter()
    memory["views"] = peak_memory_mb()

    volume = TSDFVolume(options.voxel_mm / 1000)
    for view in views:
        weights = pixel_weights(view.depth, view.mask, view.K, GRAZING_EXPONENT[options.depth], options.edge_px)
        volume.integrate(view.depth, weights, view.K, view.world_to_camera)
    fused = volume.extract_mesh(options.weight_threshold)
    if "positions" not in fused.vertex or len(fused.vertex.positions) == 0:
        raise MVPSError("the fused mesh is empty: the views' depths do not agree; check the poses, or use a larger "
                        "voxel_mm (--voxel-mm)")
    mesh = clean_mesh(fused, options.hole_mm / 1000)
    positions = mesh.vertex.positions.numpy().astype(np.float64)
    normals = mesh.vertex.normals.numpy().astype(np.float64)
    colouring = ViewColours(views, options.edge_px, positions, normals)
    mesh.vertex.colors = o3d.core.Tensor(colouring.vertex_colours(positions, normals).astype(np.float32))
    t_fusion = time.perf_counter()
    memory["fusion"] = peak_memory_mb()
    textured = options.texture_px > 0 and texture_mesh(mesh, colouring, options.texture_px)
    memory["texture"] = peak_memory_mb()
    info = {"references": [capture.frame_id(k) for k in references],
            "failed": {str(k): e for k, e in failed.items()},
            "retried": {str(k): e for k, e in retried.items()},
            "views": [{"reference": v.reference, "seconds": round(v.seconds, 3), **v.selection} for v in views],
            "azimuth_span_deg": round(span, 1), "goes_around": goes_around, "depth": options.depth,
            "voxel_mm": options.voxel_mm, "up": up_direction(poses).tolist(), "vertices": len(positions),
            "triangles": int(len(mesh.triangle.indices)), "textured": bool(textured),
            "timings": {"plan": t_plan - t0, "views": t_views - t_plan, "fusion": t_fusion - t_views,
                        "texture": time.perf_counter() - t_fusion, "total": time.perf_counter() - t0},
            "capture_frames": n_given, "registered_frames": kept,
            "dropped_frames": {str(i): why for i, why in dropped.items()},
            "stage_peak_memory_mb": memory, "workers_peak_memory_mb": workers_peak_memory_mb()}
    return Reconstruction(mesh, views, failed, goes_around, span, up_direction(poses), options.voxel_mm / 1000, info)


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 1


#: The whole-object mesh of a folder written by ``o3d-mvps reconstruct`` (vertex colours, normals).
RECONSTRUCTION_MESH = "mesh.ply"


def is_reconstruction_folder(folder) -> bool:
    """Whether ``folder`` was written by ``o3d-mvps reconstruct`` (mesh.ply and report.json, no depth.npy)."""
    from pathlib import Path

    root = Path(folder)
    return (root / RECONSTRUCTION_MESH).is_file() and (root / "report.json").is_file() and \
        not (root / "depth.npy").is_file()


def read_reconstruction(folder) -> tuple[o3d.t.geometry.TriangleMesh, dict]:
    """(mesh, report) of a folder written by ``o3d-mvps reconstruct``: mesh.ply (metres, frame-0
    camera, vertex colours and normals; the folder's mesh.obj/.glb hold the albedo texture) and
    report.json.

    Raises MVPSError naming the file when either cannot be read.
    """
    import json
    from pathlib import Path

    root = Path(folder)
    path = root / RECONSTRUCTION_MESH
    if not path.is_file():
        raise MVPSError(f"{root} is not a reconstruct folder ({RECONSTRUCTION_MESH} missing); give the folder that "
                        "'o3d-mvps reconstruct' wrote")
    mesh = o3d.t.io.read_triangle_mesh(str(path))
    if "indices" not in mesh.triangle or len(mesh.triangle.indices) == 0:
        raise MVPSError(f"{path} holds no triangles; reconstruct again ('o3d-mvps reconstruct CAPTURE {root}')")
    try:
        report = json.loads((root / "report.json").read_text())
    except (OSError, ValueError) as e:
        raise MVPSError(f"cannot read {root / 'report.json'} ({e}); reconstruct again") from None
    return mesh, report


def view_warnings(views: list) -> list[str]:
    """The workers' warnings of the views (each with ``reference`` and ``warnings``), each message
    once with the views that raised it; the views whose refinement leant on the sensor for weak
    coverage (:data:`~o3d_mvps.covisibility.WEAK_COVERAGE_NOTE`) in one message with the remedy."""
    said, weak = {}, []
    for view in views:
        for message in view.warnings:
            if WEAK_COVERAGE_NOTE in message:
                weak.append(view.reference)
            else:
                said.setdefault(message, []).append(view.reference)
    messages = [f"{_views_named(references)}: {message}" for message, references in said.items()]
    if weak:
        messages.append(f"{_views_named(weak)} (of {len(views)}): fewer than {MIN_WELL_COVISIBLE} of the frames see "
                        f"at least {MOST_OF_REFERENCE:.0%} of the reference's surface, so the refinement leans on the "
                        f"sensor depth there ({WEAK_COVERAGE_NOTE}); frames at most 20 degrees apart all round the "
                        "object (18 or more for a whole ring) give every view photometric detail")
    return messages


def _views_named(references: list) -> str:
    """'reference view 3' or 'reference views 0, 3, 5'."""
    return f"reference view{'s' if len(references) > 1 else ''} {', '.join(map(str, references))}"
