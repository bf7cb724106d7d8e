"""Builds the simulator's compiled kernel (torchdoct/sim/_kernel.c); everything else is in pyproject.toml.

The extension is optional: without a C compiler the package installs and runs on the bit-identical
torch reference (torchdoct.sim.kernel), more slowly. ``-ffp-contract=off`` keeps every multiply and
add a separate IEEE operation, as in the reference (the flags are those of ``kernel.CFLAGS``);
``--param=vect-partial-vector-usage=2`` lets GCC finish vector loops with masked vectors instead of
scalar iterations (other compilers build without it).
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CFLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c11"]
OPTIONAL_CFLAGS = ["--param=vect-partial-vector-usage=2"]


class BuildExt(build_ext):
    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception:  # a compiler that does not take the optional flags: build without them
            ext.extra_compile_args = list(CFLAGS)
            super().build_extension(ext)


setup(
    ext_modules=[
        Extension(
            "torchdoct.sim._kernel",
            ["torchdoct/sim/_kernel.c"],
            optional=True,
            extra_compile_args=CFLAGS + OPTIONAL_CFLAGS,
        )
    ],
    cmdclass={"build_ext": BuildExt},
)
