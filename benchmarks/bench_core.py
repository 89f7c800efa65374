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
    args = ap.parse_args(argv)
    if not ccore.available():
        print("the compiled core is not built or is turned off (HBVM_MD_CORE)")
        return 1
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
