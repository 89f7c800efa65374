"""Benchmark (not a test): REBOUNDx's own unit tests run with HBVM in place of IAS15.

REBOUNDx's tests are not part of this repository (REBOUNDx is a GPL-3 project of its own): fetch
them and give their files on the command line::

    git clone --depth 1 https://github.com/dtamayo/reboundx
    python benchmarks/bench_reboundx_tests.py reboundx/reboundx/tests/test_tides_spin*.py

REBOUND's own tests run the same way (``rebound/tests/test_*.py`` of REBOUND's repository, or
of the installed package's ``rebound/tests``, which match the installed version).

Each file runs twice in a fresh Python process, with ``unittest``: as written (IAS15, REBOUND's
default), and with every simulation it creates starting with ``sim.integrator = "hbvm"`` (a
simulation it loads from a file keeps the integrator it was saved with).  Each test's outcome
and time are printed side by side; the exit status is 1 when a test passes with IAS15 and not
with HBVM.  Nothing is written.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

_CHILD = r"""
import json, os, sys, time, unittest, warnings
warnings.simplefilter("ignore")
path, integ, out = sys.argv[1:4]
sys.path.insert(0, os.path.dirname(path))
import rebound
if integ == "hbvm":
    import hbvm_md  # noqa: F401  (registers "hbvm")
    init = rebound.Simulation.__init__
    def __init__(self, *a, **k):
        init(self, *a, **k)
        if not a and not k:                 # (a new simulation, not one loaded from a file)
            self.integrator = "hbvm"
    rebound.Simulation.__init__ = __init__
os.chdir(os.path.dirname(out))             # (tests write their files in the working folder)
suite = unittest.defaultTestLoader.loadTestsFromName(
    os.path.splitext(os.path.basename(path))[0])
res = {}
def each(s):
    for t in s:
        if isinstance(t, unittest.TestSuite):
            yield from each(t)
        else:
            yield t
for t in each(suite):
    r = unittest.TestResult()
    t0 = time.perf_counter()
    t.run(r)
    el = time.perf_counter() - t0
    bad = r.failures + r.errors
    res[t.id()] = dict(ok=r.wasSuccessful(), time=el,
                       message=(bad[0][1].strip().splitlines()[-1] if bad else ""))
json.dump(res, open(out, "w"))
"""


def run(path: str, integ: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "result.json")
        env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
        p = subprocess.run([sys.executable, "-c", _CHILD, os.path.abspath(path), integ, out],
                           env=env, capture_output=True, text=True)
        if not os.path.exists(out):
            raise RuntimeError(f"{path} with {integ} did not run: {p.stderr[-2000:]}")
        with open(out) as fh:
            return json.load(fh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", help="REBOUNDx or REBOUND test files (test_*.py)")
    args = ap.parse_args()
    worse = 0
    print("| test | IAS15 | HBVM | time HBVM / IAS15 |")
    print("|---|---|---|---|")
    for path in args.files:
        ias, hb = run(path, "ias15"), run(path, "hbvm")
        for name in ias:
            a, b = ias[name], hb.get(name, dict(ok=False, time=float("nan"), message="not run"))
            worse += a["ok"] and not b["ok"]
            show = lambda r: "pass" if r["ok"] else f"FAIL ({r['message'][:80]})"  # noqa: E731
            print(f"| {name.split('.', 1)[1]} | {show(a)} | {show(b)} | "
                  f"{b['time'] / a['time']:.2f} |", flush=True)
    sys.exit(1 if worse else 0)


if __name__ == "__main__":
    main()
