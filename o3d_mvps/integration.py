"""Open3D integration: refine a list of ``o3d.t.geometry.RGBDImage`` directly.

People with Open3D reconstruction scripts hold RGB-D frames as ``o3d.t.geometry.RGBDImage``
and a ``PinholeCameraIntrinsic``. :func:`refine_rgbd` turns such a list into a
:class:`~o3d_mvps.capture.Capture`, runs :func:`o3d_mvps.refine` and hands back Open3D types:
the reference frame's RGB-D image with super-resolved depth, ready for
``o3d.t.geometry.VoxelBlockGrid.integrate`` or ``o3d.t.geometry.PointCloud.create_from_rgbd_image``
(``depth_scale=1.0``: the depth is float32 metres), and the refined camera poses.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .capture import Capture, default_depth_intrinsic, image_from_array, to_host, validate_capture
from .capture.validation import check_light
from .errors import CaptureError
from .model.camera import as_intrinsic_matrix
from .model.resampling import resample_valid
from .model.sensor import check_depth_unit, choose_scale_factor
from .solver.device import check_device
from .solver.options import RefineOptions
from .solving import refine


def refine_rgbd(
    rgbd_images,
    intrinsic,
    *,
    scale_factor: int | None = None,
    options: RefineOptions | None = None,
    masks=None,
    depth_scale: float = 1000.0,
    initial_poses=None,
    light: str = "led",
    device="CPU:0",
) -> tuple[list, np.ndarray]:
    """Refine the first of a list of RGB-D frames: super-resolved depth at colour resolution.

    Frame 0 is the reference: the solver estimates depth, albedo and lighting for the
    reference view only, using the other frames (lit differently by the LED) as photometric
    constraints, and refines every frame's pose. So the result is **one** RGB-D image, the
    refined reference, in a list (the list form lets a loop over several references
    concatenate results). To refine other views, call again with that frame first, or
    reconstruct the whole object with :func:`o3d_mvps.reconstruct`.

    Parameters
    ----------
    rgbd_images : list of o3d.t.geometry.RGBDImage
        n >= 1 frames of one object, reference first, all of one size. Colour (H, W, 3):

        - ``uint8`` (or ``uint16``): sRGB-encoded camera values, linearised here;
        - ``float32``/``float64``: **linear** RGB in [0, 1] (not sRGB).

        Depth (h, w) or (h, w, 1), registered to the colour camera, 0 = no measurement:

        - ``uint16``: units of ``1 / depth_scale`` metres (millimetres by default);
        - ``float32``/``float64``: metres.

        Either at the depth sensor's native resolution, h = H / SF and w = W / SF, or already
        at colour resolution (h = H, w = W, e.g. aligned by ``RSBagReader``); in the second
        case pass ``scale_factor`` and each SF x SF block is averaged over its valid
        (nonzero) pixels down to the native grid, which the model's depth prior expects.
    intrinsic : o3d.camera.PinholeCameraIntrinsic or (3, 3) array or o3d.core.Tensor
        Pinhole intrinsics of the **colour** camera in pixels (of the W x H colour images).
        The depth grid's intrinsics follow from SF (:func:`~o3d_mvps.capture.default_depth_intrinsic`).
    scale_factor : int, optional
        Super-resolution factor SF. Default: H / h (so depth given at colour resolution
        without ``scale_factor`` is refined at SF 1, i.e. no super-resolution). When given
        with native-resolution depth it must equal H / h.
    options : RefineOptions, optional
        Solver options (default ``RefineOptions()``). With ``options.frames`` only those
        frames are used, the first of them being the reference.
    masks : list, optional
        One entry per frame: None, or an (H, W) / (H, W, 1) array or ``o3d.t.geometry.Image``
        (nonzero = object). The reference mask bounds the returned depth; without one the
        whole depth coverage is refined, so segment the object when you can.
    depth_scale : float
        Units per metre of ``uint16`` depth (1000 = millimetres). Ignored for float depth.
    initial_poses : (n, 4, 4) array, optional
        Poses reference -> frame i to start from, e.g. from Open3D's reconstruction system
        (invert its camera-to-world poses and multiply by the reference's). Default: Open3D
        ICP odometry on the sensor depth, which registers the frames in list order, so order
        the frames along the camera path.
    light : {"led", "room"}
        What lit the frames (a capture folder's ``capture.json`` "light"): the LED on the camera
        (default) or room light; picks the light model unless ``options.light_model`` is set.
    device : str or o3d.core.Device
        Where the solver runs: "CPU:0" (default) or "CUDA:0" (:func:`o3d_mvps.refine`'s), whatever
        device the frames are on. The frames are read on the host either way (the image pyramid
        is built there).

    Returns
    -------
    refined : list of o3d.t.geometry.RGBDImage
        ``[reference]``: the reference frame's colour image exactly as given, and depth
        (H, W, 1) float32 **metres** at colour resolution, 0 outside the reference mask.
        Integrate it with ``depth_scale=1.0``; ``VoxelBlockGrid.integrate`` takes float depth
        only with float colour: pass ``color.to(o3d.core.float32, scale=1 / 255)`` for uint8.
    poses : (n, 4, 4) float64 ndarray
        Refined camera poses mapping reference-camera coordinates to frame-i coordinates
        (``poses[0]`` is the identity), for the frames used (all n by default). With the
        reference camera as the world frame, ``poses[i]`` is exactly the world -> camera
        ``extrinsic`` Open3D's integrators (``VoxelBlockGrid.integrate``) take for frame i.

    Raises
    ------
    CaptureError
        Empty list or a non-RGBDImage entry, missing or invalid intrinsics, frames of mixed
        sizes, colour not a multiple of depth or of ``scale_factor``, depth in the wrong unit,
        or another inconsistency found by :func:`~o3d_mvps.capture.validate_capture`.

    Examples
    --------
    >>> refined, poses = o3d_mvps.refine_rgbd(frames, intrinsic)        # doctest: +SKIP
    >>> color = refined[0].color.to(o3d.core.float32, scale=1 / 255)  # doctest: +SKIP
    >>> vbg.integrate(coords, refined[0].depth, color, K, extrinsic, 1.0, 3.0)  # doctest: +SKIP
    """
    check_light(light)
    check_device(device)
    capture = capture_from_rgbd(rgbd_images, intrinsic, scale_factor=scale_factor, masks=masks,
                                depth_scale=depth_scale)
    capture.light = light
    refinement = refine(capture, options, device, initial_poses=initial_poses)
    reference = refinement.info["frames"][0]
    depth = np.ascontiguousarray(refinement.depth_array()[..., None], dtype=np.float32)
    color = rgbd_images[reference].color
    depth_image = image_from_array(depth).to(color.device)  # on the frames' device (e.g. CUDA:0); no copy on CPU
    refined = o3d.t.geometry.RGBDImage(color, depth_image, True)
    return [refined], refinement.poses.numpy()


def capture_from_rgbd(rgbd_images, intrinsic, *, scale_factor: int | None = None, masks=None,
                      depth_scale: float = 1000.0) -> Capture:
    """The validated :class:`~o3d_mvps.capture.Capture` of a list of RGB-D frames.

    Conversions and arguments as in :func:`refine_rgbd`: colour becomes (H, W, 3) float32
    linear RGB (uint8/uint16 sRGB kept as codes, which the capture decodes), depth (H/SF, W/SF, 1) float32 metres; colour intrinsics (3, 3) float64, depth
    intrinsics those of the area-averaged grid.

    Raises
    ------
    CaptureError
        See :func:`refine_rgbd`.
    """
    frames = _check_list(rgbd_images)
    K = _colour_intrinsic(intrinsic)
    colour = [_pixels(f.color) for f in frames]
    depth = [_pixels(f.depth) for f in frames]
    H, W = _common_size(colour, "colour")
    h, w = _common_size(depth, "depth")
    _check_intrinsic_size(intrinsic, (H, W))
    sf = choose_scale_factor((H, W), (h, w), scale_factor, exact=True)
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise CaptureError(f"depth_scale {depth_scale!r} must be a positive number (1000 for millimetres)")

    depth_m = [_depth_metres(d, depth_scale, i) for i, d in enumerate(depth)]
    if (h, w) == (H, W) and sf > 1:
        # a block keeps the mean of its valid pixels (any one suffices)
        depth_m = [resample_valid(d, d > 0, (h // sf, w // sf), min_valid_fraction=1e-6)[0] for d in depth_m]
    capture = Capture(
        color=[image_from_array(_linear_colour(c, i)) for i, c in enumerate(colour)],
        depth=[image_from_array(d.astype(np.float32)[..., None]) for d in depth_m],
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, sf)),
        masks=_masks(masks, len(frames)),
        depth_scale=float(depth_scale),
        sensor="open3d RGBDImage",
    )
    validate_capture(capture, [f"rgbd_images[{i}]" for i in range(len(frames))])
    return capture


# --- helpers ---------------------------------------------------------------------------------


def _check_list(rgbd_images) -> list:
    if rgbd_images is None or isinstance(rgbd_images, o3d.t.geometry.RGBDImage):
        raise CaptureError("rgbd_images must be a list of o3d.t.geometry.RGBDImage (reference first); "
                           "wrap a single frame in a list")
    frames = list(rgbd_images)
    if not frames:
        raise CaptureError("rgbd_images is empty; pass at least one o3d.t.geometry.RGBDImage (ideally ~20 LED-lit "
                           "frames, the reference first)")
    for i, frame in enumerate(frames):
        if not isinstance(frame, o3d.t.geometry.RGBDImage):
            hint = (" (a legacy o3d.geometry.RGBDImage: build o3d.t.geometry.RGBDImage(color, depth) from "
                    "o3d.t.geometry.Image instead, keeping the colour)"
                    if isinstance(frame, o3d.geometry.RGBDImage) else "")
            raise CaptureError(f"rgbd_images[{i}] is a {type(frame).__name__}, not an o3d.t.geometry.RGBDImage{hint}")
        if frame.color.is_empty() or frame.depth.is_empty():
            raise CaptureError(f"rgbd_images[{i}] has an empty colour or depth image; give both")
    return frames


def _colour_intrinsic(intrinsic) -> np.ndarray:
    if intrinsic is None:
        raise CaptureError("the colour camera intrinsics are missing: pass intrinsic= an "
                           "o3d.camera.PinholeCameraIntrinsic or a 3x3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    try:
        return as_intrinsic_matrix(to_host(intrinsic))
    except (ValueError, TypeError) as e:
        raise CaptureError(f"intrinsic: {e}") from None


def _check_intrinsic_size(intrinsic, colour_size) -> None:
    """A PinholeCameraIntrinsic knows its image size: it must be the colour size."""
    if isinstance(intrinsic, o3d.camera.PinholeCameraIntrinsic) and intrinsic.width > 0 and intrinsic.height > 0:
        H, W = colour_size
        if (intrinsic.height, intrinsic.width) != (H, W):
            raise CaptureError(
                f"the intrinsics are for {intrinsic.width}x{intrinsic.height} images but the colour frames are "
                f"{W}x{H} (WxH); pass the colour camera's intrinsics (not the depth camera's)"
            )


def _pixels(image) -> np.ndarray:
    """(rows, cols[, C]) numpy array of an o3d.t.geometry.Image on any device."""
    return to_host(image.as_tensor())


def _common_size(arrays, kind: str) -> tuple[int, int]:
    first = arrays[0].shape[:2]
    for i, a in enumerate(arrays):
        if a.shape[:2] != first:
            raise CaptureError(
                f"{kind} of rgbd_images[{i}] is {a.shape[1]}x{a.shape[0]} but rgbd_images[0]'s is "
                f"{first[1]}x{first[0]} (WxH); every frame must have the same size, resample or drop the odd one"
            )
    return first


def _depth_metres(depth: np.ndarray, depth_scale: float, i: int) -> np.ndarray:
    """(h, w) float64 metres of a uint16 (units 1/depth_scale m) or float (metres) depth image."""
    d = depth[..., 0] if depth.ndim == 3 and depth.shape[2] == 1 else depth
    if d.ndim != 2:
        raise CaptureError(f"depth of rgbd_images[{i}] has shape {depth.shape}; depth must be single-channel")
    if d.dtype == np.uint16:
        z, unit = d.astype(np.float64) / depth_scale, f"uint16 with depth_scale {depth_scale:g}"
        fix = "pass the right depth_scale (1000 for millimetres, 10000 for 0.1 mm)"
    elif d.dtype in (np.float32, np.float64):
        z, unit = d.astype(np.float64), "float"
        fix = "float depth must be in metres: divide millimetres by 1000, or pass uint16 depth with depth_scale"
    else:
        raise CaptureError(f"depth of rgbd_images[{i}] is {d.dtype}; use uint16 (with depth_scale) or float32 metres")
    if not np.all(np.isfinite(z)) or (z < 0).any():
        raise CaptureError(f"depth of rgbd_images[{i}] has NaN, inf or negative values; use 0 for no measurement")
    check_depth_unit(z, f"depth of rgbd_images[{i}] ({unit})", fix)
    return z


def _linear_colour(colour: np.ndarray, i: int) -> np.ndarray:
    """(H, W, 3) colour of a capture: uint8/uint16 sRGB codes kept as they are (the capture's
    ``color_encoding`` "srgb" decodes them: :meth:`~o3d_mvps.capture.Capture.color_array`), float
    linear colour as float32."""
    if colour.ndim != 3 or colour.shape[2] not in (3, 4):
        raise CaptureError(f"colour of rgbd_images[{i}] has shape {colour.shape}; colour must be (H, W, 3) RGB")
    rgb = colour[..., :3]
    if rgb.dtype in (np.uint8, np.uint16):
        return rgb
    if rgb.dtype in (np.float32, np.float64):
        return rgb.astype(np.float32)  # range checked by validate_capture
    raise CaptureError(f"colour of rgbd_images[{i}] is {rgb.dtype}; use uint8 sRGB or float32 linear RGB in [0, 1]")


def _masks(masks, n: int):
    if masks is None:
        return None
    masks = list(masks)
    if len(masks) != n:
        raise CaptureError(f"{len(masks)} masks for {n} frames; give one entry per frame (None = no mask)")
    out = []
    for m in masks:
        if m is None:
            out.append(None)
            continue
        a = (_pixels(m) if hasattr(m, "as_tensor") else np.asarray(to_host(m))) != 0
        a = a.astype(np.uint8) * np.uint8(255)
        out.append(image_from_array(a[..., None] if a.ndim == 2 else a))  # shape checked by validate_capture
    return out
