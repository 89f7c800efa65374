"""Ctrl-C during a long compiled fixed-step run (issue 37, item 3): the compiled loop runs in
chunks of about ``engine.CHUNK_SECONDS``, so the interrupt is honoured between two of them,
with the committed steps in the exception's ``result``; the numbers are those of one
uninterrupted call of the loop, bit for bit, whatever the chunks."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from integrators import HBVM, Stepper, integrate
from integrators import engine
from integrators.records import Samples
from systems import Kepler, outer_solar_system

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _one_call(method, system, y0, h, steps, sample_every):
    """The run as one call of the step loop (what Stepper.run did before the chunks)."""
    st = Stepper(method, system, y0)
    b = st.binding
    n = steps // sample_every + 1
    out_t, out_y, out_e = np.full(n, np.nan), np.empty((n, y0.size)), np.full(n, np.nan)
    b.step_code.run(b.system_record, st._state_record(), h, st._extrapolation(h, None),
                    b.method_record, b.no_newton,
                    st._options("fixed_point"),
                    b.work_record(st.counters), Samples(steps, sample_every, out_t, out_y, out_e))
    return out_t, out_y, out_e, st.counters.copy()


@pytest.mark.parametrize("scene", ["kepler", "outer solar system"])
@pytest.mark.parametrize("seconds", [1e-12, None, 1e9])
@pytest.mark.parametrize("sample_every", [1, 7, 1000])
def test_chunks_give_the_numbers_of_one_call(scene, seconds, sample_every, monkeypatch):
    """One step a chunk (1e-12 s), the default, and chunks growing 8x each call (1e9 s): the
    samples, the final state and the counters are those of one call of the loop."""
    if scene == "kepler":
        system, method, h, steps = Kepler(0.6), HBVM(6, 3), 2 * np.pi / 50, 700
    else:
        system, method, h, steps = outer_solar_system(), HBVM(9, 6), 200.0, 300
    y0 = system.initial_state()
    if seconds is not None:
        monkeypatch.setattr(engine, "CHUNK_SECONDS", seconds)
    res = integrate(method, system, y0, h, steps, sample_every=sample_every)
    t, y, e, counters = _one_call(method, system, y0, h, steps, sample_every)
    assert np.array_equal(res.t, t) and np.array_equal(res.y, y) and np.array_equal(res.energy, e)
    assert (res.steps, res.nfev, res.iterations) == (int(counters[0]), int(counters[2]),
                                                     int(counters[1]))


def test_a_failed_step_inside_a_chunk_keeps_the_steps_before_it(monkeypatch):
    """A step that fails mid-run (Kepler e = 0.999 coming back to pericentre) stops the
    chunks where one call stops: the same committed steps and samples."""
    from integrators import StepError
    kep = Kepler(0.999)
    y0 = kep.exact_solution(kep.initial_state(), 1.0).astype(float)      # past pericentre
    monkeypatch.setattr(engine, "CHUNK_SECONDS", 1e-12)
    with pytest.raises(StepError) as info:
        integrate(HBVM(8, 4), kep, y0, 2 * np.pi / 1000, 2000, sample_every=3,
                  solver="fixed_point")
    res = info.value.result
    t, y, e, counters = _one_call(HBVM(8, 4), kep, y0, 2 * np.pi / 1000, 2000, 3)
    n = len(res.t)
    assert 0 < res.steps == int(counters[0]) < 2000
    assert np.array_equal(res.y, y[:n]) and np.array_equal(res.t, t[:n])


CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from integrators import HBVM, integrate
    from systems import Kepler
    kep = Kepler(0.6)
    y0 = kep.initial_state()
    h = 2 * np.pi / 100
    integrate(HBVM(6, 3), kep, y0, h, 1000)                  # compiled and loaded
    per_step = float("inf")
    for _ in range(3):      # the fastest of three: a loaded machine makes the run longer, not shorter
        t0 = time.perf_counter()
        integrate(HBVM(6, 3), kep, y0, h, 30000, sample_every=1000)
        per_step = min(per_step, (time.perf_counter() - t0) / 30000)
    steps = int(20.0 / per_step) // 1000 * 1000             # a run of at least about 20 s
    print("ready", steps, flush=True)
    t0 = time.perf_counter()
    try:
        integrate(HBVM(6, 3), kep, y0, h, steps, sample_every=1000)
        print("finished", flush=True)
    except KeyboardInterrupt as err:
        res = err.result
        ref = integrate(HBVM(6, 3), kep, y0, h, (len(res.t) - 1) * 1000, sample_every=1000)
        same = np.array_equal(res.y, ref.y) and np.array_equal(res.energy, ref.energy)
        print("interrupted", res.status, res.steps, len(res.t), same,
              time.perf_counter() - t0, flush=True)
""")


def test_ctrl_c_stops_a_long_compiled_run_and_keeps_its_steps():
    """SIGINT about 1 s into a compiled run of about 20 s: KeyboardInterrupt, status
    "interrupted", far fewer steps than requested, and the samples those of an uninterrupted
    run of as many steps."""
    if not hasattr(signal, "SIGINT") or sys.platform == "win32":
        pytest.skip("POSIX signals")
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    try:
        line = proc.stdout.readline().split()
        assert line and line[0] == "ready", proc.stderr.read()
        requested = int(line[1])
        time.sleep(1.0)
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    words = out.split()
    assert words and words[0] == "interrupted", (out, err)
    status, steps, samples, same = words[1], int(words[2]), int(words[3]), words[4]
    assert status == "interrupted" and same == "True"
    assert 0 < samples - 1 <= steps // 1000 and steps < requested // 4, (steps, requested)
