"""Build of the optional compiled planner kernel (everything else is in pyproject.toml).

``deft_gym.planner._lattice_c`` is the lattice planner's evaluation step, its resampling of
predicted obstacles and its longitudinal profiles in C, bit-identical to their numpy versions (which are used when the
extension is missing: ``optional=True`` turns a failed build into a warning). IEEE semantics are kept: no fast-math, no FMA contraction.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "deft_gym.planner._lattice_c",
            ["deft_gym/planner/_lattice_c.c"],
            extra_compile_args=["-O2", "-std=c99", "-fno-fast-math", "-ffp-contract=off"],
            optional=True,
        )
    ]
)
