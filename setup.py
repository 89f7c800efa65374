"""The compiled core (integrators/csrc), built by ``pip install``: a C11 extension,
``integrators._core``; and REBOUND's compiled glue (hbvm_md/rebound/csrc),
``hbvm_md.rebound._glue``, built against the installed REBOUND's ``rebound.h`` (as REBOUNDx
builds: REBOUND's wheel ships its headers in site-packages/src) and the slot numbers of
``hbvm_md/rebound/layout.py``, written into ``hbvm_layout.h`` here.

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
GLUE_SOURCES = ["hbvm_md/rebound/csrc/glue.c"]


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _layout_header(out: Path) -> None:
    """hbvm_layout.h: the statuses and sizes of hbvm_md/rebound/layout.py as ``RB_<name>``; and
    hbvm_layout_check.h: a static assertion, for every member of csrc/hbvm_state.h's two
    structs, that its offsetof is the slot layout.py read from the header for the Python host
    and the numba step (so that the compiler checks the reading)."""
    lay = _load("_hbvm_layout", Path(__file__).parent / "hbvm_md" / "rebound" / "layout.py")
    members = {"SL_" + k.upper() for k in lay.STATE} | {k.upper() for k in lay.CONTEXT}
    lines = ["/* written by setup.py from hbvm_md/rebound/layout.py: do not edit */",
             "#ifndef HBVM_LAYOUT_H", "#define HBVM_LAYOUT_H"]
    for name, value in sorted(vars(lay).items()):
        if (name.isupper() and type(value) is int and not name.startswith("_")
                and name not in members):
            lines.append(f"#define RB_{name} ({value})")
    lines.append("#endif")
    out.mkdir(parents=True, exist_ok=True)
    (out / "hbvm_layout.h").write_text("\n".join(lines) + "\n")
    check = ["/* written by setup.py: layout.py's reading of hbvm_state.h, checked */",
             "#include <stddef.h>"]
    for struct, table in (("hbvm_rb_state", lay.STATE), ("hbvm_rb_context", lay.CONTEXT)):
        for member, slot in table.items():
            check.append(f"_Static_assert(offsetof(struct {struct}, {member}) == 8 * {slot}, "
                         f'"layout.py reads {struct}.{member} at slot {slot}");')
    (out / "hbvm_layout_check.h").write_text("\n".join(check) + "\n")


def _rebound_include() -> tuple[str, str]:
    """The installed REBOUND's header folder and version (its wheel's site-packages/src)."""
    spec = importlib.util.find_spec("rebound")
    if spec is None or spec.origin is None:
        raise RuntimeError("REBOUND is not installed in the build environment")
    pkg = Path(spec.origin).parent
    for inc in (pkg.parent / "src", pkg / "include", pkg.parent.parent / "src"):
        if (inc / "rebound.h").exists():
            break
    else:
        raise RuntimeError(f"rebound.h not found beside {pkg}")
    version = "?"
    for dist in pkg.parent.glob("rebound-*.dist-info"):
        version = dist.name[len("rebound-"):-len(".dist-info")]
    return str(inc), version


def _source_digest() -> str:
    """The digest of the core's sources built into the extension (integrators/_digest.py, loaded
    by its path): integrators.ccore refuses a core older than its sources (an editable install
    whose C changed and was not rebuilt, or whose rebuild failed)."""
    here = Path(__file__).parent
    return _load("_hbvm_digest", here / "integrators" / "_digest.py").source_digest(here)


def _glue_digest() -> str:
    here = Path(__file__).parent
    return _load("_hbvm_digest", here / "integrators" / "_digest.py").glue_digest(here)


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
        if ext.name == "hbvm_md.rebound._glue":
            inc, version = _rebound_include()
            gen = Path(self.build_temp) / "hbvm_layout"
            _layout_header(gen)
            ext.include_dirs = [str(gen), inc, "integrators/csrc"]
            digest = [f'-DHBVM_SOURCE_DIGEST="{_glue_digest()}"',
                      f'-DHBVM_REBOUND_VERSION="{version}"']
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
                             optional=True),
                   # needs the core (its step, through the capsule integrators._core.API) and
                   # REBOUND's header; without it REBOUND's step is numba's (hbvm_md.rebound.cglue)
                   Extension("hbvm_md.rebound._glue", sources=GLUE_SOURCES,
                             depends=["integrators/csrc/hbvm_core.h",
                                      "hbvm_md/rebound/csrc/hbvm_state.h",
                                      "hbvm_md/rebound/layout.py"],
                             optional=True)],
      cmdclass={"build_ext": BuildCore})
