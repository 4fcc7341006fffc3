"""The compiled kernels, built when a C compiler is there (pyproject.toml has the rest).

``app.core.localise._plane_kernel`` (the localiser's plane fits, ``surface.py``) and
``app.core.localise._knn_kernel`` (each point's k nearest neighbours, ``neighbourhoods.py``) are
optional: without a compiler the build warns and goes on, and the numpy and pykdtree passes they
replace run instead (``tests/core/test_plane_kernel.py`` and ``tests/core/test_knn_kernel.py``
check both give the same results and labels).
"""

import sys

from setuptools import Extension, setup

# no fused multiply-adds: the kernel follows numpy's arithmetic operation by operation
CONTRACTION = [] if sys.platform == "win32" else ["-ffp-contract=off"]

setup(
    ext_modules=[
        Extension(
            f"app.core.localise.{name}",
            [f"app/core/localise/{name}.c"],
            extra_compile_args=CONTRACTION,
            optional=True,
        )
        for name in ("_plane_kernel", "_knn_kernel")
    ]
)
