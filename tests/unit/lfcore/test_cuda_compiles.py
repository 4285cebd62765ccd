"""Every Warp kernel module compiles to CUDA for the H100 (sm_90), with or without a GPU.

The CUDA variants of the kernel tests run only where Warp finds a GPU, which CI has not. Warp
ships NVRTC, though, so the CUDA code of every kernel can be generated and compiled anywhere: a
kernel that builds for the CPU but not for CUDA (a construct only the CUDA backend rejects, a
tile kernel) fails here, before anyone holds a GPU.
"""

from __future__ import annotations

import importlib
import pkgutil

import pytest

import lfcore._kernels as kernel_package
from lfcore.device import warp

#: The H100's compute capability, the GPU the benchmarks run on.
ARCH = 90

MODULES = sorted(m.name for m in pkgutil.iter_modules(kernel_package.__path__))


@pytest.mark.parametrize("name", MODULES)
def test_kernel_module_compiles_for_cuda(name, tmp_path):
    wp = warp()
    if ARCH not in wp.get_cuda_supported_archs():
        pytest.skip(f"this Warp build cannot compile CUDA for sm_{ARCH}")
    module = importlib.import_module(f"lfcore._kernels.{name}")
    if not any(isinstance(v, wp.Kernel) for v in vars(module).values()):
        return  # functions and structs only: compiled with the modules that use them
    (binary,) = wp.compile_aot_module(module, arch=ARCH, module_dir=tmp_path)
    assert binary.stat().st_size > 0
