"""Benchmark (not a test): the compiled core's step against the numba step, in one process.

The engine's fixed steps on HLW's outer solar system (``systems.outer_solar_system``) for a few
HBVM(k, s) settings: CPU time a step (the process's, around ``integrate``; the fastest of
``--rounds`` rounds, the two steps alternated within a round, each after a warm-up run), the
ratio core / numba taken in each round, the sweeps a step (force evaluations / k / steps) and
the largest relative energy error; medians over ``--starts`` starts perturbed by 1e-9 in the
positions.  Both steps give the same numbers bit for bit (tests/test_core.py), so the sweeps
and errors are one column.  ``--asm`` also counts the packed instructions of the hot functions
in the built core (objdump), by register width.  Writes ``benchmarks/results/core.md``.

    python benchmarks/bench_core.py [--steps 20000] [--rounds 3] [--starts 3] [--asm]

For the split of a step between its pieces, build the core with its pieces kept apart
(``HBVM_MD_PROFILE=1 pip install -e .``) and run ``perf record python benchmarks/bench_core.py
--only core`` then ``perf report``.

``--followers N``: the same comparison with N test particles added to the outer solar system
(massless, on near-circular orbits between 36 and 50 AU: the followers of
``integrators.followers``, in groups of ``core.FOLLOWER_GROUP``), HBVM(9, 8) at 500 days and
HBVM(7, 6) at 250 days: the engine's ``Stepper.run``, CPU time a step (the fastest of
``--rounds`` rounds of ``--steps`` steps, core and numba alternated, after a warm-up), and a
fresh process with empty caches running the scene on the core (its wall time, and the files
numba left in its cache: none) and on numba (its wall time: the compile a new user waits for).
Writes ``benchmarks/results/core_followers.md``.

    python benchmarks/bench_core.py --followers 1000 [--steps 300] [--rounds 5]
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from hbvm_md.reports.machine import machine  # noqa: E402
from integrators import HBVM, ccore, integrate  # noqa: E402
from systems import outer_solar_system  # noqa: E402

SETTINGS = [(9, 8, 500.0), (16, 8, 500.0), (8, 8, 500.0), (10, 8, 500.0), (6, 3, 100.0),
            (12, 6, 200.0)]
HOT = ("hbvm_nbody_force", "stage_positions", "project", "project_compensated", "hbvm_run")


def one(mode: str, k: int, s: int, h: float, y0, steps: int):
    os.environ["HBVM_MD_CORE"] = mode
    system = outer_solar_system()
    t0 = time.process_time()
    r = integrate(HBVM(k, s), system, y0, h, steps, sample_every=max(steps // 50, 1))
    took = time.process_time() - t0
    err = float(np.max(np.abs(r.energy / r.energy[0] - 1)))
    return took / steps * 1e6, r.nfev / (k * steps), err


FOLLOWER_SETTINGS = [(9, 8, 500.0), (7, 6, 250.0)]


def with_particles(n: int, seed: int = 0):
    """The outer solar system and n massless particles between 36 and 50 AU."""
    from systems import NBody
    base = outer_solar_system()
    rng = np.random.default_rng(seed)
    r = rng.uniform(36.0, 50.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    x = np.stack([r * np.cos(phi), r * np.sin(phi), rng.normal(0, 0.02, n) * r], axis=1)
    v = (np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], axis=1)
         * (np.sqrt(base.G / r) * rng.uniform(0.9, 1.1, n))[:, None])
    return NBody(np.concatenate([base.body_masses, np.zeros(n)]), G=base.G,
                 positions=np.concatenate([base.positions, x]),
                 velocities=np.concatenate([base.velocities, v]))


def one_followers(mode: str, k: int, s: int, h: float, system, steps: int):
    """CPU time a step (us) of the engine's Stepper.run after a warm-up, iterations a step."""
    from integrators import Stepper
    os.environ["HBVM_MD_CORE"] = mode
    st = Stepper(HBVM(k, s), system, system.initial_state())
    assert isinstance(st.binding.step_code, ccore.CoreStep) == (mode == "core")
    st.run(h, 5, sample_every=5)
    n0, it0 = st.counters[0], st.counters[1]
    t0 = time.process_time()
    st.run(h, steps, sample_every=steps)
    took = time.process_time() - t0
    return took / steps * 1e6, (st.counters[1] - it0) / (st.counters[0] - n0)


def cold(mode: str, n: int, k: int, s: int, h: float, steps: int = 20) -> tuple[float, int]:
    """A fresh process with empty caches running the scene: (its wall time in s, the files
    numba and the step's cache left)."""
    import tempfile
    code = (f"import sys; sys.path.insert(0, {HERE!r}); from bench_core import with_particles; "
            f"from integrators import HBVM, integrate; sc = with_particles({n}); "
            f"integrate(HBVM({k}, {s}), sc, sc.initial_state(), {h}, {steps})")
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=os.path.join(tmp, "numba"),
                   HBVM_MD_CACHE_DIR=os.path.join(tmp, "hbvm"), HBVM_MD_CORE=mode,
                   PYTHONPATH=os.path.dirname(HERE))
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        files = sum(len(f) for _, _, f in os.walk(tmp))
    return wall, files


def main_followers(args) -> int:
    system = with_particles(args.followers)
    steps = args.steps if args.steps != 20000 else 300
    rows = []
    for k, s, h in FOLLOWER_SETTINGS:
        for mode in ("core", "numba"):
            one_followers(mode, k, s, h, system, 20)           # warm-up (numba compiles here)
        best = {"core": np.inf, "numba": np.inf}
        ratios = []
        for _ in range(args.rounds):
            got = {mode: one_followers(mode, k, s, h, system, steps) for mode in best}
            for mode in best:
                best[mode] = min(best[mode], got[mode][0])
            ratios.append(got["core"][0] / got["numba"][0])
        its = got["core"][1]
        rows.append((k, s, h, best, statistics.median(ratios), its))
        print(f"HBVM({k}, {s}) h={h:g}, {args.followers} test particles: core "
              f"{best['core']:.0f} us, numba {best['numba']:.0f} us, ratio "
              f"{statistics.median(ratios):.2f}, {its:.2f} iterations a step", flush=True)
    k, s, h = FOLLOWER_SETTINGS[0]
    wall_core, files_core = cold("core", args.followers, k, s, h)
    wall_numba, files_numba = cold("numba", args.followers, k, s, h)
    print(f"fresh process, empty caches, 20 steps: core {wall_core:.1f} s ({files_core} files "
          f"cached), numba {wall_numba:.1f} s ({files_numba} files cached)", flush=True)
    load = os.getloadavg()
    lines = ["# The compiled core against the numba step: test particles", "",
             "Written by `benchmarks/bench_core.py --followers "
             f"{args.followers}`: the engine's fixed steps (`Stepper.run`) on HLW's outer solar "
             f"system with {args.followers} massless test particles between 36 and 50 AU "
             "(followers: the sources' stage equations first, then each particle's in their "
             "field with its own stop rule), CPU time a step, the fastest of "
             f"{args.rounds} rounds of {steps} steps, core and numba alternated; the ratio is "
             "the median of the rounds'. Both give the same numbers bit for bit "
             "(tests/test_core.py), so the iterations are one column.", "",
             f"Machine: {machine()}; load average (1, 5, 15 min): {load[0]:.1f}, {load[1]:.1f}, "
             f"{load[2]:.1f}; the core's vector width: {ccore.lanes()} doubles "
             f"(build flags: `{ccore._core.BUILD_FLAGS}`).", "",
             "| method | h (days) | core (us/step) | numba (us/step) | core / numba | "
             "iterations a step |", "|---|---:|---:|---:|---:|---:|"]
    for k, s, h, best, ratio, its in rows:
        lines.append(f"| HBVM({k}, {s}) | {h:g} | {best['core']:.0f} | {best['numba']:.0f} | "
                     f"{ratio:.2f} | {its:.2f} |")
    lines += ["", f"A fresh process with empty caches (`NUMBA_CACHE_DIR`, `HBVM_MD_CACHE_DIR`) "
              f"taking 20 steps of HBVM({FOLLOWER_SETTINGS[0][0]}, {FOLLOWER_SETTINGS[0][1]}) "
              f"on the same scene, wall time including Python's start and imports: on the core "
              f"{wall_core:.1f} s, {files_core} files left in the caches (nothing compiled); on "
              f"numba {wall_numba:.1f} s, {files_numba} files (the step compiled for the "
              "scene)."]
    out = os.path.join(HERE, "results", "core_followers.md")
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def packed(functions=HOT) -> dict:
    """{function: {width: packed arithmetic instructions}} of the built core (objdump -d)."""
    if ccore._core is None:
        return {}
    out = subprocess.run(["objdump", "-d", "--no-show-raw-insn", ccore._core.__file__],
                         capture_output=True, text=True).stdout
    counts, current = {}, None
    for line in out.splitlines():
        m = re.match(r"^[0-9a-f]+ <([^>]+)>:", line)
        if m:
            name = m.group(1).split(".")[0]
            current = name if name in functions else None
            continue
        if current is None:
            continue
        ins = re.search(r"\t(v(?:add|sub|mul|div|sqrt|fn?m(?:add|sub)\w*)pd)\s+(.*)", line)
        if ins:
            reg = re.search(r"%([xyz])mm", ins.group(2))
            width = {"x": 128, "y": 256, "z": 512}[reg.group(1)] if reg else 0
            d = counts.setdefault(current, {})
            key = f"{ins.group(1)} {width}-bit"
            d[key] = d.get(key, 0) + 1
    return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--only", choices=("core", "numba"), default=None)
    ap.add_argument("--asm", action="store_true")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "core.md"))
    ap.add_argument("--followers", type=int, default=0,
                    help="N test particles added to the scene (writes core_followers.md)")
    args = ap.parse_args(argv)
    if not ccore.available():
        print("the compiled core is not built or is turned off (HBVM_MD_CORE)")
        return 1
    if args.followers > 0:
        return main_followers(args)
    modes = [args.only] if args.only else ["core", "numba"]
    base = outer_solar_system().initial_state()
    rng = np.random.default_rng(0)
    rows = []
    for k, s, h in SETTINGS:
        per_start = []
        for start in range(args.starts):
            y0 = base.copy()
            m = y0.size // 2
            y0[:m] *= 1.0 + 1e-9 * rng.standard_normal(m)
            for mode in modes:                       # warm-up (numba compiles here)
                one(mode, k, s, h, y0, 200)
            best = {mode: np.inf for mode in modes}
            ratios = []
            for _ in range(args.rounds):
                got = {mode: one(mode, k, s, h, y0, args.steps) for mode in modes}
                for mode in modes:
                    best[mode] = min(best[mode], got[mode][0])
                if len(modes) == 2:
                    ratios.append(got["core"][0] / got["numba"][0])
            sweeps, err = got[modes[0]][1], got[modes[0]][2]
            per_start.append((best, ratios, sweeps, err))
        med = {mode: statistics.median(p[0][mode] for p in per_start) for mode in modes}
        ratio = (statistics.median(r for p in per_start for r in p[1])
                 if len(modes) == 2 else float("nan"))
        sweeps = statistics.median(p[2] for p in per_start)
        err = statistics.median(p[3] for p in per_start)
        rows.append((k, s, h, med, ratio, sweeps, err))
        print(f"HBVM({k}, {s}) h={h:g}: " + ", ".join(f"{mo} {med[mo]:.2f} us" for mo in modes)
              + (f", ratio {ratio:.2f}" if len(modes) == 2 else "")
              + f", {sweeps:.2f} sweeps, energy error {err:.1e}", flush=True)
    if args.only:
        return 0
    load = os.getloadavg()
    lines = ["# The compiled core against the numba step", "",
             "Written by `benchmarks/bench_core.py`: the engine's fixed steps on HLW's outer "
             "solar system, CPU time a step (the fastest of "
             f"{args.rounds} rounds of {args.steps} steps, the two steps alternated), medians "
             f"over {args.starts} starts perturbed by 1e-9; the ratio is taken in each round. "
             "Both steps give the same numbers bit for bit, so the sweeps and the energy error "
             "are one column.", "",
             f"Machine: {machine()}; load average (1, 5, 15 min): {load[0]:.1f}, {load[1]:.1f}, "
             f"{load[2]:.1f}; the core's vector width: {ccore.lanes()} doubles "
             f"(build flags: `{ccore._core.BUILD_FLAGS}`).", "",
             "| method | h (days) | core (us/step) | numba (us/step) | core / numba | sweeps a step "
             "| energy error |", "|---|---:|---:|---:|---:|---:|---:|"]
    for k, s, h, med, ratio, sweeps, err in rows:
        lines.append(f"| HBVM({k}, {s}) | {h:g} | {med['core']:.2f} | {med['numba']:.2f} | "
                     f"{ratio:.2f} | {sweeps:.2f} | {err:.1e} |")
    if args.asm:
        lines += ["", "Packed arithmetic instructions of the hot functions (objdump -d of the "
                  "built core), by register width:", "", "| function | instructions |",
                  "|---|---|"]
        for fn, d in packed().items():
            lines.append(f"| `{fn}` | " + ", ".join(f"{k} x{v}" for k, v in sorted(d.items()))
                         + " |")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
