"""The paper's model pieces: camera and SE(3), normals, shading, warping, robust weights.

Pure numpy/scipy functions on arrays; Open3D types stay at the package boundary.
"""

from .parallel import configure_openmp

configure_openmp()  # before the first parallel kernel loads OpenMP (model.parallel)
