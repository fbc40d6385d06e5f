"""The build: setuptools (pyproject.toml), and the package's kernels compiled into the built
package, so that an install's first call loads them instead of compiling them
(``src/knnrefine/_engine/shipped.py``). Not in an editable install (the source is the
package there: kernels compile at first use, as before), nor with
KNNREFINE_BUILD_KERNELS=0; a build that cannot compile them says so and builds the package
without them (they compile at first use then)."""

import os
import shutil
import subprocess
import sys

from setuptools import setup
from setuptools.command.build_py import build_py

try:
    from setuptools.command.bdist_wheel import bdist_wheel
except ImportError:  # setuptools before 70.1
    from wheel.bdist_wheel import bdist_wheel

COMPILE = "import sys; from knnrefine._engine import shipped; shipped.build(sys.argv[1])"


class build_py_and_kernels(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        if not kernels_asked():
            print("knnrefine: KNNREFINE_BUILD_KERNELS=0: kernels compile at first use")
            return
        root = os.path.abspath(self.build_lib)
        package = os.path.join(root, "knnrefine")
        for folder, dirs, _ in os.walk(package):  # an earlier build's kernels
            if "__pycache__" in dirs:
                shutil.rmtree(os.path.join(folder, "__pycache__"))
                dirs.remove("__pycache__")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
        done = subprocess.run([sys.executable, "-c", COMPILE, root], env=env, check=False)
        if done.returncode != 0:
            print("knnrefine: the kernels could not be compiled at build time; they compile "
                  "at first use instead", file=sys.stderr)  # fmt: skip


def kernels_asked():
    return os.environ.get("KNNREFINE_BUILD_KERNELS", "1").strip() != "0"


class bdist_wheel_for_this_platform(bdist_wheel):
    """A wheel with compiled kernels is this platform's and this Python's (its tag says so:
    the kernels are x86-64 Linux code, say, in files named for CPython 3.11)."""

    def finalize_options(self):
        super().finalize_options()
        if kernels_asked():
            self.root_is_pure = False


setup(cmdclass={"build_py": build_py_and_kernels, "bdist_wheel": bdist_wheel_for_this_platform})
