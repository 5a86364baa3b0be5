"""What numpy computes with on this machine: its version, the SIMD extensions its kernels dispatch to, and
its BLAS with the core type that BLAS chose. Recorded beside every summary, study and session file, since
the last bits of exp, power, cbrt (numpy's AVX-512 kernels) and of a solve or matmul (OpenBLAS's kernel per
core) depend on them (issue 53). A simulated story does not (docs/development.md);
a plan, a benchmark's figure or a live cell's numbers may, and this says where to look first."""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import numpy as np


def _blas_core() -> str:
    """OpenBLAS's choice of kernels (``OPENBLAS_CORETYPE`` or its own detection), or "" when the BLAS
    is not an OpenBLAS this can ask."""
    libs = Path(np.__file__).parent.parent / "numpy.libs"
    for lib in sorted(libs.glob("libscipy_openblas*.so*")) if libs.is_dir() else []:
        try:
            so = ctypes.CDLL(str(lib))  # already loaded by numpy: the same handle
        except OSError:
            continue
        for name in ("scipy_openblas_get_corename64_", "openblas_get_corename"):
            fn = getattr(so, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return (fn() or b"").decode(errors="replace")
    return ""


@functools.cache
def numeric_build() -> str:
    """One line, e.g. "numpy 2.4.6 (SIMD X86_V3 X86_V4 AVX512_ICL), scipy-openblas 0.3.31 (Haswell)"."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    simd = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    blas = np.show_config(mode="dicts").get("Build Dependencies", {}).get("blas", {})
    core = _blas_core()
    return (
        f"numpy {np.__version__} (SIMD {' '.join(simd) or 'baseline only'}), "
        f"{blas.get('name', 'BLAS')} {blas.get('version', '?')}" + (f" ({core})" if core else "")
    )
