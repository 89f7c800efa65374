"""The compiled core (integrators/csrc), built by ``pip install``: a C11 extension,
``integrators._core``.

By default it is compiled for the installing machine (``-march=native``: the vector width of
its processor, AVX-512 where it has it); ``HBVM_MD_PORTABLE=1`` builds a baseline binary that
runs on any processor of the architecture (a wheel, a container image shared between machines);
``HBVM_MD_PROFILE=1`` keeps the step's pieces apart for a profiler (``perf``).
A compiler that rejects ``-march=native`` gets the baseline flags. ``-ffp-contract=off``: no
fused multiply-add where the source has none, so that every build gives the same numbers
(the explicit ``fma`` of the compensated sums stays); ``-fno-math-errno`` lets ``sqrt`` run
in the vector lanes.
"""
import importlib.util
import os
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

BASE = ["-O3", "-std=c11", "-ffp-contract=off", "-fno-math-errno"]
NATIVE = ["-march=native"]
SOURCES = ["integrators/csrc/pymodule.c", "integrators/csrc/hbvm_step.c",
           "integrators/csrc/kernels_nbody.c", "integrators/csrc/kernels_simple.c"]


def _source_digest() -> str:
    """The digest of the core's sources built into the extension (integrators/_digest.py, loaded
    by its path): integrators.ccore refuses a core older than its sources (an editable install
    whose C changed and was not rebuilt, or whose rebuild failed)."""
    here = Path(__file__).parent
    spec = importlib.util.spec_from_file_location("_hbvm_digest",
                                                  here / "integrators" / "_digest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.source_digest(here)


def _profile() -> list:
    """HBVM_MD_PROFILE=1: the step's pieces kept apart for a profiler (same numbers)."""
    on = os.environ.get("HBVM_MD_PROFILE", "").strip() not in ("", "0")
    return ["-DHBVM_PROFILE", "-g"] if on else []


def _portable() -> bool:
    return os.environ.get("HBVM_MD_PORTABLE", "").strip() not in ("", "0")


class BuildCore(build_ext):
    """Build with the machine's own instruction set, else the portable baseline."""

    def build_extension(self, ext):
        flags = (BASE if _portable() else BASE + NATIVE) + _profile()
        digest = [f'-DHBVM_SOURCE_DIGEST="{_source_digest()}"']
        ext.extra_compile_args = flags + digest + [f'-DHBVM_BUILD_FLAGS="{" ".join(flags)}"']
        try:
            super().build_extension(ext)
        except Exception:
            if flags == BASE:
                raise
            self.warn("the compiler refused -march=native: building the portable core")
            flags = BASE + _profile()
            ext.extra_compile_args = flags + digest + [f'-DHBVM_BUILD_FLAGS="{" ".join(flags)}"']
            super().build_extension(ext)


setup(ext_modules=[Extension("integrators._core", sources=SOURCES,
                             depends=["integrators/csrc/hbvm_core.h", "integrators/csrc/hbvm_vec.h"], libraries=["m"],
                             # without a C compiler the package installs without its core and
                             # the numba step serves (integrators.ccore)
                             optional=True)],
      cmdclass={"build_ext": BuildCore})
