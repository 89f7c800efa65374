"""Benchmark (not a test): ASE's own tests that run NVE molecular dynamics, run as written and
with :class:`hbvm_md.HBVMDynamics` (its defaults) in ``VelocityVerlet``'s place.

ASE ships its tests inside the installed package (``ase/test``); by default this runs every
test file there that uses ``VelocityVerlet`` (the MD tests of ``ase/test/md``, the Hookean and
RATTLE constraint tests, the force curve, ...; those that need an external code or an optional
package skip, as they do without HBVM)::

    python benchmarks/bench_ase_tests.py                  # ASE's files that use VelocityVerlet
    python benchmarks/bench_ase_tests.py FILE [FILE ...]  # or the files given

Each set runs twice with pytest, each in a fresh process: as written, and with a pytest plugin
loaded before collection that replaces ``ase.md.VelocityVerlet`` and
``ase.md.verlet.VelocityVerlet`` by a subclass of ``HBVMDynamics`` taking VelocityVerlet's
arguments (``timestep`` or ``dt``, ``trajectory``, ``logfile``, ``loginterval``,
``append_trajectory``), so that every test module that imports VelocityVerlet gets HBVM.  Each
test's outcome is printed side by side, with the number of HBVMDynamics the second run created
(so that a swap that did not take is seen).  The exit status is 1 when a test passes as written
and not with HBVM.  Nothing is written.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: the pytest plugin of the HBVM run (imported before collection, so a test module's
#: ``from ase.md import VelocityVerlet`` already finds the substitute)
_PLUGIN = r'''
import os
import ase.md
import ase.md.verlet
from hbvm_md.ase import HBVMDynamics

_COUNT = os.environ["HBVM_ASE_TESTS_COUNT"]


class VelocityVerlet(HBVMDynamics):
    """HBVMDynamics with its defaults, taking VelocityVerlet's arguments."""

    def __init__(self, atoms, timestep=None, trajectory=None, logfile=None, loginterval=1,
                 dt=None, append_trajectory=False, **kwargs):
        with open(_COUNT, "a") as fh:
            fh.write("1\n")
        if append_trajectory:
            kwargs["append_trajectory"] = True
        super().__init__(atoms, timestep if timestep is not None else dt,
                         trajectory=trajectory, logfile=logfile, loginterval=loginterval,
                         **kwargs)


ase.md.VelocityVerlet = VelocityVerlet
ase.md.verlet.VelocityVerlet = VelocityVerlet
'''


def ase_files() -> list[str]:
    """The files of the installed ASE's test folder that use VelocityVerlet."""
    import ase
    top = os.path.join(os.path.dirname(ase.__file__), "test")
    if not os.path.isdir(top):
        raise SystemExit(f"the installed ASE has no test folder ({top}); give the files")
    out = []
    for d, _, names in os.walk(top):
        for n in names:
            if n.startswith("test_") and n.endswith(".py"):
                p = os.path.join(d, n)
                with open(p) as fh:
                    if "VelocityVerlet" in fh.read():
                        out.append(p)
    return sorted(out)


def run(files: list[str], hbvm: bool) -> tuple[dict, int]:
    """{test id: 'pass' | 'skip' | 'FAIL (message)'} of one pytest run, and the number of
    HBVMDynamics it created."""
    with tempfile.TemporaryDirectory() as tmp:
        xml, count = os.path.join(tmp, "result.xml"), os.path.join(tmp, "count")
        open(count, "w").close()
        path = [ROOT, os.environ.get("PYTHONPATH", "")]
        args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                f"--junitxml={xml}", *files]
        if hbvm:
            with open(os.path.join(tmp, "hbvm_swap.py"), "w") as fh:
                fh.write(_PLUGIN)
            path.insert(0, tmp)
            args[3:3] = ["-p", "hbvm_swap"]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(path), HBVM_ASE_TESTS_COUNT=count,
                   MPLBACKEND="Agg")
        p = subprocess.run(args, env=env, capture_output=True, text=True, cwd=tmp)
        if not os.path.exists(xml):
            raise RuntimeError(f"pytest did not run: {p.stdout[-2000:]} {p.stderr[-2000:]}")
        res = {}
        for case in ET.parse(xml).getroot().iter("testcase"):
            name = f"{case.get('classname')}::{case.get('name')}"
            bad = case.find("failure") if case.find("failure") is not None else case.find("error")
            if bad is not None:
                res[name] = f"FAIL ({(bad.get('message') or '').splitlines()[0][:80]})"
            elif case.find("skipped") is not None:
                res[name] = "skip"
            else:
                res[name] = "pass"
        with open(count) as fh:
            return res, len(fh.read().split())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", help="ASE test files (default: those of the installed "
                                             "ASE that use VelocityVerlet)")
    args = ap.parse_args()
    files = [os.path.abspath(f) for f in args.files] or ase_files()
    vv, _ = run(files, hbvm=False)
    hb, made = run(files, hbvm=True)
    print("| test | as written | HBVMDynamics in VelocityVerlet's place |")
    print("|---|---|---|")
    worse = 0
    for name in sorted(set(vv) | set(hb)):
        a, b = vv.get(name, "not run"), hb.get(name, "not run")
        worse += a == "pass" and b != "pass"
        print(f"| {name.split('ase.test.', 1)[-1]} | {a} | {b} |")
    def tally(res: dict) -> str:
        ok, skip = (sum(r == v for r in res.values()) for v in ("pass", "skip"))
        return f"{ok} pass, {len(res) - ok - skip} fail, {skip} skip"
    print(f"\nwith HBVM: {tally(hb)}; as written: {tally(vv)}; {made} HBVMDynamics created")
    sys.exit(1 if worse else 0)


if __name__ == "__main__":
    main()
