"""The one compiled kernel, built when a C compiler is there (pyproject.toml has the rest).

``app.core.localise._plane_kernel`` (the localiser's plane fits, ``surface.py``) is optional:
without a compiler the build warns and goes on, and the numpy passes it replaces run instead
(``tests/core/test_plane_kernel.py`` checks both give the same planes and labels).
"""

import sys

from setuptools import Extension, setup

# no fused multiply-adds: the kernel follows numpy's arithmetic operation by operation
CONTRACTION = [] if sys.platform == "win32" else ["-ffp-contract=off"]

setup(
    ext_modules=[
        Extension(
            "app.core.localise._plane_kernel",
            ["app/core/localise/_plane_kernel.c"],
            extra_compile_args=CONTRACTION,
            optional=True,
        )
    ]
)
