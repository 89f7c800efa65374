"""Benchmark (not a test): the first run on a fresh machine (issue 36, item 5).

Each measurement is a new Python process with new, empty cache folders (``HBVM_MD_CACHE_DIR``
and ``NUMBA_CACHE_DIR``), that imports hbvm-md and runs a first scene:

* **REBOUND**: a star and two Jupiter-mass planets, ``sim.integrator = "hbvm"``,
  ``sim.integrate(1.0)`` at dt = 0.01 (the REBOUND step compiled for this scene);
* **ASE**: a 13-atom copper icosahedron with ASE's EMT, ``HBVMDynamics(atoms, 2 fs).run(5)``
  (the compiled core calling the calculator back; before it, the compiled pieces the Python
  step called);
* **engine**: the outer solar system through ``integrate(HBVM(9, 8), ..., 500.0, 200)`` (the
  N-body kernel of the compiled core; before it, the numba step compiled for the scene);

then the same again with the caches it filled (what every later run pays).  Reported: wall
time of the first run (the import excluded) and the process's CPU time (import included: on a
loaded machine the CPU time is the steadier figure), medians over ``--rounds``.  The peer is
heyoka's LLVM compile of the same three-body scene (``taylor_adaptive``, tol 1e-15), which it
pays in every new process.  ``--compare DIR`` also runs another source tree of hbvm-md (for
example the previous commit, ``git worktree add DIR HEAD~1``) in the same rounds, alternated
with this one.  Writes ``benchmarks/results/cold_start.md``.

    python benchmarks/bench_cold_start.py [--rounds 3] [--compare DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from hbvm_md.reports.machine import machine  # noqa: E402

REBOUND = """
    import time
    t0 = time.perf_counter()
    import rebound, hbvm_md
    t1 = time.perf_counter()
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.05)
    sim.add(m=1e-3, a=1.6, e=0.02, inc=0.1)
    sim.integrator = "hbvm"
    sim.dt = 0.01
    sim.integrate(1.0)
    t2 = time.perf_counter()
"""
ASE = """
    import time
    t0 = time.perf_counter()
    from ase.cluster import Icosahedron
    from ase.calculators.emt import EMT
    from ase import units
    from hbvm_md import HBVMDynamics
    t1 = time.perf_counter()
    atoms = Icosahedron("Cu", 2)
    atoms.calc = EMT()
    HBVMDynamics(atoms, 2 * units.fs).run(5)
    t2 = time.perf_counter()
"""
ENGINE = """
    import time
    t0 = time.perf_counter()
    from integrators import HBVM, integrate
    from systems import outer_solar_system
    t1 = time.perf_counter()
    system = outer_solar_system()
    integrate(HBVM(9, 8), system, system.initial_state(), 500.0, 200)
    t2 = time.perf_counter()
"""
SCENES = {"REBOUND three-body": REBOUND, "ASE Cu13 EMT": ASE, "engine outer solar system": ENGINE}
HEYOKA = """
    import time
    t0 = time.perf_counter()
    import numpy as np, heyoka as hy
    if hasattr(hy.llvm_state, "set_diskcache_enabled"):
        hy.llvm_state.set_diskcache_enabled(False)   # (heyoka >= 7.10 caches compiled code on disk)
    t1 = time.perf_counter()
    sys_ = hy.model.nbody(3, masses=[1.0, 1e-3, 1e-3], Gconst=1.0)
    state = np.array([0, 0, 0, 0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 1.6, 0, 0, 0, 0.79, 0.0])
    ta = hy.taylor_adaptive(sys_, state, tol=1e-15)
    ta.propagate_until(1.0)
    t2 = time.perf_counter()
"""
REPORT = """
    import json, time
    print(json.dumps({"first": t2 - t1, "cpu": time.process_time()}))
"""


def run(code: str, tree: str, cache: str) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, HBVM_MD_CACHE_DIR=cache,
               NUMBA_CACHE_DIR=os.path.join(cache, "numba"))
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code) + textwrap.dedent(REPORT)],
                       capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    if r.returncode != 0:
        raise RuntimeError(f"the scene failed in {tree}:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--compare", default=None, help="another hbvm-md source tree, run alternately")
    ap.add_argument("--label", default="compared", help="its name in the table (a commit, say)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "cold_start.md"))
    ap.add_argument("--scenes", default=",".join(SCENES),
                    help="comma-separated, of: " + ", ".join(SCENES))
    args = ap.parse_args(argv)
    trees = [("this tree", ROOT)] + ([(args.label, os.path.abspath(args.compare))]
                                     if args.compare else [])
    load = os.getloadavg()
    rows: dict = {}
    for r in range(args.rounds):
        for label, tree in trees:
            for scene in args.scenes.split(","):
                code = SCENES[scene]
                cache = tempfile.mkdtemp(prefix="hbvm-md-cold-")
                try:
                    cold, warm = run(code, tree, cache), run(code, tree, cache)
                finally:
                    shutil.rmtree(cache, ignore_errors=True)
                rows.setdefault((scene, label), []).append((cold, warm))
                print(f"round {r + 1} {label:9s} {scene:18s} first run {cold['first']:6.1f} s "
                      f"(cpu {cold['cpu']:5.1f} s), cached {warm['first']:5.2f} s", flush=True)
        try:
            rows.setdefault(("heyoka three-body (peer)", "heyoka"), []).append(
                (run(HEYOKA, ROOT, tempfile.gettempdir()), None))
        except RuntimeError as exc:
            print(f"heyoka: not measured ({str(exc).splitlines()[-1]})")
    lines = ["# First run on empty compile caches", "",
             "Written by `benchmarks/bench_cold_start.py` (issue 36, item 5). A new process with "
             "empty `HBVM_MD_CACHE_DIR` and `NUMBA_CACHE_DIR` imports hbvm-md and runs a first "
             "scene, then a second process runs it again with the caches filled. Medians over "
             f"{args.rounds} rounds; the trees alternate within a round. Wall times exclude the "
             "import; CPU times are the whole process's (on a loaded machine the steadier "
             "figure).", "",
             f"Machine: {machine()}; load average at the start (1, 5, 15 min): "
             f"{load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f}.", "",
             "| scene | code | first run wall (s) | first run CPU (s) | cached run wall (s) |",
             "|---|---|---:|---:|---:|"]
    for (scene, label), v in rows.items():
        first = np.median([c["first"] for c, _ in v])
        cpu = np.median([c["cpu"] for c, _ in v])
        warm = np.median([w["first"] for _, w in v]) if v[0][1] is not None else float("nan")
        lines.append(f"| {scene} | {label} | {first:.1f} | {cpu:.1f} | "
                     + ("" if np.isnan(warm) else f"{warm:.2f}") + " |")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
