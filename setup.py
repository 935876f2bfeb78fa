"""Build of the optional compiled kernels (everything else is in pyproject.toml).

``deft_gym.planner._lattice_c`` is the lattice planner's evaluation step, its resampling of
predicted obstacles (and their relevance test) and its longitudinal profiles in C;
``deft_gym.modules._control_c`` is the control module's conversion of a planned trajectory and
its nearest-point search; ``deft_gym.record._snapshot_c`` is the recorder's payload snapshot (pickle
is used without it); ``deft_gym.record._tap_c`` is the recorder's bus tap (JSON-encoding and framing
each message as an MCAP record); ``deft_gym.record._format_c`` is ``template % args`` for the
Foxglove scene's text (exact fixed-point numbers; Python's ``%`` formats what it does not take);
``deft_gym.record._scene_c`` is the scene text's values (``scene.scene_args``);
``deft_gym.bus._ros1_c`` is a payload's ROS 1 bytes (the log's binary message encoding).
All are bit-identical to the Python and numpy versions (which are used when an extension is
missing: ``optional=True`` turns a failed build into a warning). IEEE
semantics are kept: no fast-math, no FMA contraction. Each records the digests of its C source and
of the Python file it stands in for (``BUILT_FROM``): a kernel older than an edit of either is not
loaded (a warning says to rebuild: ``pip install -e .`` or ``make venv``).
"""

import hashlib
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
HERE = Path(__file__).resolve().parent


def kernel(name: str, c_source: str, mirrors: str) -> Extension:
    """A compiled kernel that records what it was built from: BUILT_FROM is the SHA-256 of its C
    source and of the Python file whose code it stands in for (``deft_gym.files.stale_kernel``
    compares them with the files beside it when the kernel is loaded: a kernel built before
    either was edited is not used - an edit of the Python version is never silently overridden)."""
    digests = " ".join(hashlib.sha256((HERE / p).read_bytes()).hexdigest() for p in (c_source, mirrors))
    return Extension(name, [c_source], extra_compile_args=FLAGS, optional=True, depends=[mirrors],
                     define_macros=[("BUILT_FROM", f'"{digests}"')])


setup(
    cmdclass={"build_py": BuildPyWithConfigs},
    ext_modules=[
        kernel("deft_gym.planner._lattice_c", "deft_gym/planner/_lattice_c.c", "deft_gym/planner/lattice.py"),
        kernel("deft_gym.modules._control_c", "deft_gym/modules/_control_c.c", "deft_gym/modules/control.py"),
        kernel("deft_gym.record._snapshot_c", "deft_gym/record/_snapshot_c.c", "deft_gym/record/worker.py"),
        kernel("deft_gym.record._tap_c", "deft_gym/record/_tap_c.c", "deft_gym/record/recorder.py"),
        kernel("deft_gym.record._format_c", "deft_gym/record/_format_c.c", "deft_gym/record/textformat.py"),
        kernel("deft_gym.record._scene_c", "deft_gym/record/_scene_c.c", "deft_gym/record/scene.py"),
        kernel("deft_gym.bus._ros1_c", "deft_gym/bus/_ros1_c.c", "deft_gym/bus/ros1.py"),
    ]
)
