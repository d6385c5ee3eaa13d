"""The depth's grid modes in a result, and the normal error a mesh shows (issue #31).

``python -m benchmarks.grid_modes RESULT CAPTURE [--json OUT.json]``

RESULT is a refine output folder (its ``depth.npy`` and ``mask.png``, metres, colour grid) and
CAPTURE the rendered capture whose ``groundtruth/`` scores it. Printed (and written as JSON):

- ``mae_central_deg``: the normal error as :func:`o3d_mvps.metrics.evaluate` scores it (central
  differences, what the solver's data term uses);
- ``mae_forward_deg``: the same with forward-difference normals, the normal of the triangle
  (p, p + u, p + v), against the true normals averaged over those three pixels (the triangle's
  own, not half a pixel off): what a mesh of the depth shows;
- ``checkerboard_um``, ``rows_um``, ``cols_um``: the median amplitude (micrometres) of the depth
  that alternates from pixel to pixel (:func:`grid_mode_amplitude`), which central differences
  do not see.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy import ndimage

#: 2x2 kernel whose output is the amplitude a of a checkerboard a (-1)^(u+v) (0 on a plane)
CHECKERBOARD = np.array([[1.0, -1.0], [-1.0, 1.0]]) / 4.0
#: third difference / 8 along a row: the amplitude a of a (-1)^u (0 on a quadratic)
ALTERNATION = np.array([-1.0, 3.0, -3.0, 1.0]) / 8.0


def grid_mode_amplitude(z: np.ndarray, mask: np.ndarray, margin: int = 2) -> dict:
    """Median amplitudes (micrometres) of z (H, W) metres's grid modes over the masked pixels whose
    kernel window lies inside ``mask`` (H, W) bool eroded by ``margin`` pixels: ``checkerboard_um``
    (:data:`CHECKERBOARD`, a (-1)^(u+v)), ``rows_um`` and ``cols_um`` (:data:`ALTERNATION` along
    rows and columns: a (-1)^u and a (-1)^v; both also see the checkerboard): the median of the
    kernel's absolute response, so that depth steps (occluding rims) do not dominate. A surface
    smooth on the pixel scale gives values far below the mode's: its third differences are its
    third derivative times the pixel size cubed."""
    z = np.asarray(z, dtype=np.float64)
    inside = np.asarray(mask, dtype=bool) & (z > 0)
    if margin > 0:
        inside = ndimage.binary_erosion(inside, np.ones((3, 3), bool), iterations=margin)
    out = {}
    for name, kernel in (("checkerboard_um", CHECKERBOARD), ("rows_um", ALTERNATION[None, :]),
                         ("cols_um", ALTERNATION[:, None])):
        response = ndimage.correlate(np.where(inside, z, 0.0), kernel, mode="constant")
        full = ndimage.correlate(inside.astype(np.float64), np.ones(kernel.shape), mode="constant") > kernel.size - 0.5
        values = np.abs(response[full & inside])
        out[name] = float(np.median(values) * 1e6) if values.size else float("nan")
    return out


def score(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, groundtruth) -> dict:
    """Central and forward (mesh) normal MAE (degrees) and RMSE (mm) of depth (H, W) metres on
    ``mask`` (H, W) against a capture's ground truth, on :func:`o3d_mvps.metrics.evaluation_mask`'s
    pixels, and the grid modes' amplitudes (:func:`grid_mode_amplitude`)."""
    from o3d_mvps.metrics import evaluate, evaluation_mask, normal_mae_deg
    from o3d_mvps.model.normals import perspective_normals
    from o3d_mvps.refinement import Refinement

    refinement = Refinement.from_arrays(np.where(mask, depth, 0.0), mask, K)
    central = evaluate(refinement, groundtruth)
    common = evaluation_mask(refinement, groundtruth)
    forward, _ = perspective_normals(np.where(mask, depth, 0.0), K, mask, scheme="forward")
    truth = np.asarray(groundtruth.normals, dtype=np.float64)
    triangle = truth.copy()  # the true normal of the triangle (p, p + u, p + v): its pixels' mean
    triangle[:-1, :-1] = truth[:-1, :-1] + truth[:-1, 1:] + truth[1:, :-1]
    triangle /= np.maximum(np.linalg.norm(triangle, axis=2, keepdims=True), 1e-12)
    return {"mae_central_deg": central["mae_deg"], "rmse_mm": central["rmse_mm"],
            "mae_forward_deg": normal_mae_deg(forward, triangle, common & np.any(forward != 0, 2)),
            **grid_mode_amplitude(depth, mask)}


def score_result(result, capture) -> dict:
    """:func:`score` of a refine output folder (``depth.npy``, ``mask.png``, ``intrinsic.json``)
    against the capture folder's ground truth."""
    import cv2

    from o3d_mvps.capture.reading import read_capture

    result = Path(result)
    cap = read_capture(capture)
    depth = np.load(result / "depth.npy")
    mask = cv2.imread(str(result / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    return score(depth, mask, cap.color_K(), cap.groundtruth)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result")
    ap.add_argument("capture")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    out = score_result(args.result, args.capture)
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
