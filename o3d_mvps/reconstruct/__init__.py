"""Whole objects: refine reference views all round a capture in parallel and fuse one mesh.

:func:`reconstruct` (``o3d-mvps reconstruct``) returns a :class:`Reconstruction`: a textured
mesh in the capture's frame-0 camera (metres) and, via ``printable_solid``, a closed solid in
millimetres. The package itself is callable, so ``o3d_mvps.reconstruct(capture, options)``
calls :func:`reconstruct`.
"""

import sys
import types

from .api import Reconstruction, ReconstructOptions, reconstruct
from .references import azimuth_span_deg, choose_references

__all__ = ["reconstruct", "Reconstruction", "ReconstructOptions", "choose_references", "azimuth_span_deg"]


class _CallablePackage(types.ModuleType):
    """This package, callable as :func:`reconstruct` (``o3d_mvps.reconstruct(capture)``)."""

    def __call__(self, *args, **kwargs):
        return reconstruct(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
