"""Build of the optional compiled kernels (everything else is in pyproject.toml).

``deft_gym.planner._lattice_c`` is the lattice planner's evaluation step, its resampling of
predicted obstacles (and their relevance test) and its longitudinal profiles in C;
``deft_gym.modules._control_c`` is the control module's conversion of a planned trajectory and
its nearest-point search; ``deft_gym.record._snapshot_c`` is the recorder's payload snapshot (pickle
is used without it). All are bit-identical to the Python and numpy versions (which are
used when an extension is missing: ``optional=True`` turns a failed build into a warning). IEEE
semantics are kept: no fast-math, no FMA contraction.
"""

import shutil
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_py import build_py


class BuildPyWithConfigs(build_py):
    """Ships the repository's ``configs/`` inside the package as ``deft_gym/configs`` (package
    data found through importlib.resources), so a non-editable install has its scenarios, ADS,
    training, evaluation and Foxglove configs. An editable install reads ``configs/`` in place."""

    def run(self) -> None:
        super().run()
        src = Path(__file__).resolve().parent / "configs"
        if src.is_dir() and not self.editable_mode:
            dst = Path(self.build_lib) / "deft_gym" / "configs"
            shutil.rmtree(dst, ignore_errors=True)
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))

FLAGS = ["-O2", "-std=c99", "-fno-fast-math", "-ffp-contract=off"]

setup(
    cmdclass={"build_py": BuildPyWithConfigs},
    ext_modules=[
        Extension("deft_gym.planner._lattice_c", ["deft_gym/planner/_lattice_c.c"],
                  extra_compile_args=FLAGS, optional=True),
        Extension("deft_gym.modules._control_c", ["deft_gym/modules/_control_c.c"],
                  extra_compile_args=FLAGS, optional=True),
        Extension("deft_gym.record._snapshot_c", ["deft_gym/record/_snapshot_c.c"], extra_compile_args=FLAGS, optional=True),
    ]
)
