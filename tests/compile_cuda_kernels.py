"""Compile every CUDA kernel of o3d_mvps.solver.cuda_kernels to PTX, without a GPU.

``python tests/compile_cuda_kernels.py [CC]`` (CC e.g. 9.0, the default) in a process where
numba.cuda is not the simulator (no NUMBA_ENABLE_CUDASIM=1): prints ``KERNEL PTX_CHARS`` per kernel
and exits 0; exits :data:`NO_NVVM` when numba finds no NVVM (the CUDA toolkit's compiler, e.g.
``pip install numba-cuda[cu12]``), 1 on a kernel without a signature here. ``--ptx-dir DIR``
also writes each kernel's PTX there (for ``ptxas -v``). tests/test_cuda_kernels.py runs it.

The argument types are those the solver passes (C-contiguous float64 arrays, float32 warped
colours, bool masks, int32 CSR indices, Python int and bool scalars).
"""

from __future__ import annotations

import sys

from numba import types

#: exit status when NVVM is not installed (the test then fails: the dev extra installs numba-cuda[cu12], which brings it)
NO_NVVM = 3


def _array(ndim: int, dtype=types.float64):
    return types.Array(dtype, ndim, "C")


_F1, _F2, _F3, _F4 = (_array(d) for d in (1, 2, 3, 4))
_COLOR = _array(3, types.float32)
#: the residuals (n, N, 3) or (N, 3) and the shading (n, N) or (N,): float32 on the GPU
#: (o3d_mvps.solver.device.ArrayDevice.residual_dtype)
_R1, _R2, _R3 = (_array(d, types.float32) for d in (1, 2, 3))

#: the arguments of _evaluate_partials
_EVALUATE = (_F1, *(_array(1, types.int64),) * 4, _F1, _F1, _array(1, types.int64), _array(1, types.int64), _F1, _F1,
             _F2, _F3, _array(4, types.float32), _array(2, types.boolean), _F2, _F2, types.boolean,
             *(types.float64,) * 4, types.boolean, _array(1, types.int32), _array(1, types.int32), _F1, _F1,
             _array(1, types.int32), _array(1, types.int32), _F1, types.float64, types.float64, _F2, _F2, _F1, _COLOR,
             _array(2, types.boolean), _R3, _R2, _R3, _F2)

#: kernel name in cuda_kernels -> argument types
SIGNATURES = {
    "_shading_residuals": (_COLOR, _F2, _R3, _F2, _array(2, types.boolean), _R2, _R3),
    "_led_irradiances_into": (_F2, _F2, _F2, _F2),
    "_led_point_gradients_into": (_F1, _F2, _F2, _F2, _F3),
    "_log1p_square_partials": (_R1, types.float64, _F1),
    "_warp_sample": (_F2, _F2, _F2, _COLOR, _array(1, types.boolean), _array(2, types.float32),
                     _array(1, types.boolean)),
    "_warp_sample_frames": (_F2, _F3, _F2, _array(4, types.float32), _array(2, types.boolean), _COLOR,
                            _array(2, types.boolean)),
    "_chebyshev_update": (_array(1, types.int32), _array(1, types.int32), _F1, _F1, _F1, _F1, types.float64, _F1,
                          _F1, _F1, _F1, _F1),
    "_chebyshev_start": (_array(1, types.int32), _array(1, types.int32), _F1, _F1, _F1, types.float64, _F1, _F1, _F1,
                         _F1),
    "_restrict_residual": (_array(1, types.int32), _array(1, types.int32), _F1, _array(1, types.int32),
                           _array(1, types.int32), _F1, _F1, _F1, _F1),
    "_prolong_restart": (_array(1, types.int32), _array(1, types.int32), _F1, _array(1, types.int32),
                         _array(1, types.int32), _F1, _F1, _F1, _F1, _F1, _F1, _F1, _F1),
    "_csr_multiply_add": (_array(1, types.int32), _array(1, types.int32), _F1, types.float64, _F1, _F1, _F1),
    "_cg_pass": (types.int64, _array(1, types.int32), _array(1, types.int32), _F1, types.boolean, types.boolean, _F1,
                 _F1, _F1, _F1, _F1, _F1, _F1, types.float64, _F1, _F2, _array(1, types.int32)),
    "_warp_gradients": (_F2, _F2, _F2, _COLOR, _F2, _F2, _F2),
    "_multigrid_cg": (types.int64, types.boolean, types.boolean,
                      *(_array(1, types.int32), _array(1, types.int32), _F1) * 4,
                      _F1, _F2, _F2, _F2, _F1, _F1, _F1, _F1, _F2, _F2, _F2, _F1, types.UniTuple(types.int64, 8 * 12),
                      types.int64,
                      types.UniTuple(types.float64, 5), types.boolean, _F1, types.boolean, types.float64, _F1, _F2),
    "_ridge_solves": (_F3, _F3, types.float64, types.float64, _F3, _F3, _F1),
    "_led_trial_partials": (_COLOR, _array(2, types.boolean), _F2, _F2, _F2, _F3, _F1, _F3, _F3, _F2,
                            types.float64, types.boolean, types.int64, _F2),
    # the data term's evaluation in one launch (gpueval): the grid's int64 pixels and neighbours,
    # the prior's int32 CSR arrays
    "_energy_partials": (_F1, *(_array(1, types.int64),) * 4, _F1, _F1, _array(1, types.int64),
                         _array(1, types.int64), _F1, _F1, _F2, _F3, _array(4, types.float32),
                         _array(2, types.boolean), _F2, _F2, types.boolean, *(types.float64,) * 4, types.boolean,
                         _array(1, types.int32), _array(1, types.int32), _F1, _F1, _array(1, types.int32),
                         _array(1, types.int32), _F1, types.float64, types.float64, _array(2, types.boolean), _F2),
    "_evaluation_partials": (_COLOR, _F2, _R3, _F2, _array(2, types.boolean), _R2, _R3, types.float64,
                             _array(1, types.int32), _array(1, types.int32), _F1, _F1, _array(1, types.int32),
                             _array(1, types.int32), _F1, types.float64, types.float64, _F1, _F2),
    "_led_fields_into": (_F1, _F2, _F2, _F2, _F3),
    "_led_shading_jacobians_into": (_F1, _F2, _F2, _F2, _F3, _F1, _F3),
    "_evaluate_partials": (_F1, *(_array(1, types.int64),) * 4, _F1, _F1, _array(1, types.int64),
                           _array(1, types.int64), _F1, _F1, _F2, _F3, _array(4, types.float32),
                           _array(2, types.boolean), _F2, _F2, types.boolean, *(types.float64,) * 4, types.boolean,
                           _array(1, types.int32), _array(1, types.int32), _F1, _F1, _array(1, types.int32),
                           _array(1, types.int32), _F1, types.float64, types.float64, _F2, _F2, _F1, _COLOR,
                           _array(2, types.boolean), _R3, _R2, _R3, _F2),
    "_albedo_update": (_R3, _array(2, types.boolean), _COLOR, _R2, types.float64, _F2, _F2, _F2, _F2),
    "_lighting_partials": (_R3, _array(2, types.boolean), _COLOR, _F2, types.float64, _R3, _F3),
    "_levenberg_damp": (_array(1, types.int32), _array(1, types.int32), _F1, types.float64, types.float64, _F1, _F1),
    # gpu3: the driver's extrapolation trials (the driver's three factors)
    "_extrapolation_trials": (_F1, _F1, _F2, _F2, types.UniTuple(types.float64, 3), _F1, _F1, _F2, _F3, _F2),
    "_depth_step": (_F1, _F1, types.float64, _F1, _F1, _F1, _F1),
    # gpujoint: the joint step's assembly, twist system, depth system, inverse and read-out
    "_joint_block": (_R3, _R2, _array(2, types.boolean), types.float64, _F2, _F1, _F3, _array(1, types.int64),
                     _array(1, types.int64), _F2, _F3, _F2, _array(4, types.float32), _F3, types.boolean,
                     types.boolean, _F2, _F2, _F2, _F2, _F2, _F2, _F3, _F4, _F4, _F1, _F2, _F3),
    "_add_stencil_transpose_rows": (*(_array(1, types.int32), _array(1, types.int32), _F1) * 2, _F3, types.int64,
                                    _F2),
    "_joint_twist_system": (_F3, _F3, types.float64, types.float64, _F3, _F1, _F2, _F3, _F1, _F2, _F1, _F2),
    "_joint_depth_system": (_array(1, types.int32), _array(1, types.int32),
                            *(_array(1, types.int64), _array(1, types.int64), _F1, _F1) * 2, *(_F1,) * 6,
                            *(types.float64, _array(1, types.int32), _array(1, types.int32), _F1) * 2, _F1, _F1,
                            *(_array(1, types.int32), _array(1, types.int32), _F1) * 2, _F1, _F1, _F1, _F1, _F1),
    "_joint_inverse": (_F3, _F3, _F1, types.float64, _F3, _F3, _F1),
    "_twist_readout": (_F2, _F1, _F3, _F1),
    # gpueval2: the LED offset's system from the light state
    "_led_offset_system": (_F1, _F2, _F2, _F2, _F3, _R3, _array(2, types.boolean), _F2, types.float64, types.int64,
                           _F3, _F3),
    "_led_evidence_sums": (_array(2, types.boolean), _F2, _R2, _F1, _F2, _F2, _F2, _F2, _F2, _F1),
    "_evaluate_albedo_partials": (*_EVALUATE, _F2, _F2, _F2),
    "_trial_energy_partials": (_F2, *_EVALUATE[1:12], _F4, *_EVALUATE[13:15], _F3, _F3, types.boolean, _F2,
                               types.float64, types.boolean, *_EVALUATE[23:32], _array(3, types.boolean), _F3),
    "_albedo_evaluation_partials": (_R3, _array(2, types.boolean), _COLOR, _R2, types.float64, _F2, _F2, _F2, _F2,
                                    _R3, _F2, _array(1, types.int32), _array(1, types.int32), _F1, _F1,
                                    _array(1, types.int32), _array(1, types.int32), _F1, types.float64,
                                    types.float64, _F1, _F2),
    # gpukrylov: the device multigrid's set-up (level 0's CSR, the coarser levels', P's and R's indptr and indices)
    "_multigrid_setup": (_array(1, types.int32), _array(1, types.int32), _F1, _array(1, types.int32),
                         _array(1, types.int32), _F1, *(_array(1, types.int32),) * 4, _F1, _F2, _F3, _F1,
                         types.UniTuple(types.int64, 8 * 12), types.int64),
    "_prior_gradient": (*(_array(1, types.int32), _array(1, types.int32), _F1) * 3, types.boolean, _F1, _F1,
                        types.float64, types.float64, _F1),
}


def _compiling_for(cc: tuple):
    """numba-cuda compiles the functions behind an ``overload`` (``cuda.cg.this_grid()``: the
    cooperative kernels' grid sync) for the current device's compute capability, which needs a
    GPU: here it is ``cc`` instead (the kernel's own compile_ptx takes cc as given)."""
    import types as pytypes

    from numba.cuda import dispatcher

    dispatcher.get_current_device = lambda: pytypes.SimpleNamespace(compute_capability=cc)


def main(argv: list[str]) -> int:
    from numba import cuda
    from numba.cuda.cudadrv import nvvm

    if cuda.config.ENABLE_CUDASIM:
        print("numba.cuda is the simulator here: run without NUMBA_ENABLE_CUDASIM=1")
        return 1
    if not nvvm.is_available():
        print("numba finds no NVVM (CUDA toolkit): install numba-cuda[cu12] to compile CUDA kernels")
        return NO_NVVM
    from o3d_mvps.solver import cuda_kernels

    cc = tuple(int(v) for v in (argv[0] if argv and not argv[0].startswith("-") else "9.0").split("."))
    _compiling_for(cc)
    ptx_dir = argv[argv.index("--ptx-dir") + 1] if "--ptx-dir" in argv else None
    found = {name for name, obj in vars(cuda_kernels).items()
             if isinstance(obj, cuda.dispatcher.CUDADispatcher) and not obj.targetoptions["device"]}
    if found != set(SIGNATURES):
        print(f"kernels without a signature here: {sorted(found - set(SIGNATURES))}; "
              f"signatures of no kernel: {sorted(set(SIGNATURES) - found)}")
        return 1
    for name, argtypes in SIGNATURES.items():
        ptx, _ = cuda.compile_ptx(getattr(cuda_kernels, name).py_func, argtypes, cc=cc)
        if ptx_dir is not None:
            with open(f"{ptx_dir}/{name}.ptx", "w") as file:
                file.write(ptx)
        print(name, len(ptx))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
