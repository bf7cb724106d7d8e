"""Builds the simulator's compiled kernel (torchdoct/sim/_kernel.c); everything else is in pyproject.toml.

The extension is optional: without a C compiler the package installs and runs on the bit-identical
torch reference (torchdoct.sim.kernel), more slowly. ``-ffp-contract=off`` keeps every multiply and
add a separate IEEE operation, as in the reference.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("torchdoct.sim._kernel", ["torchdoct/sim/_kernel.c"], optional=True,
                             extra_compile_args=["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c11"])])
