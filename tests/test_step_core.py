"""The one step core (issue: "One HBVM step: a single compiled core behind every path"): every
path runs the same step, failures are clear errors, compiled code is never stale."""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from integrators import (EQUIP, HBVM, ConvergenceError, NonFiniteError, StepError, Stepper,
                         UnresolvedStepError, integrate)
from systems import HamiltonianSystem, NBody, outer_solar_system
from systems.poincare import PoincareKepler
from integrators.records import StepConstants

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class Polynomial1D(HamiltonianSystem):
    """H = (p^2 + q^2) / 2 + sum c_ij q^i p^j over 3 <= i + j <= 4: not separable, degree 4."""

    dim = 1
    polynomial_degree = 4
    TERMS = [(i, n - i) for n in (3, 4) for i in range(n + 1)]

    def __init__(self, coefficients):
        self.c = np.asarray(coefficients, dtype=float)

    def energy(self, y):
        y = np.asarray(y, dtype=float)
        q, p = y[..., 0], y[..., 1]
        return 0.5 * (p * p + q * q) + sum(c * q ** i * p ** j for c, (i, j) in zip(self.c, self.TERMS))

    def gradient(self, y):
        y = np.asarray(y, dtype=float)
        q, p = y[..., 0], y[..., 1]
        dq = q + sum(c * i * q ** max(i - 1, 0) * p ** j for c, (i, j) in zip(self.c, self.TERMS) if i)
        dp = p + sum(c * j * q ** i * p ** max(j - 1, 0) for c, (i, j) in zip(self.c, self.TERMS) if j)
        return np.stack([dq, dp], axis=-1)


def test_quartic_reproduction_is_exact_with_the_default_solver():
    """H = (p^2 + q^2)/2 + q^2 p^2 / 2, y0 = (1, 0.5), h = 0.7: the first version accepted
    unconverged steps here (energy error 1e-9, no error raised)."""
    sys_ = Polynomial1D([0, 0, 0, 0, 0, 0, 0.5, 0, 0])
    for solver in ("auto", "fixed_point", "newton"):
        # (exactness at a large step: the step's own error check off)
        res = integrate(HBVM(4, 2), sys_, [1.0, 0.5], 0.7, 200, solver=solver, error_bound=None)
        assert res.steps == 200 and res.max_energy_error <= 1e-13, (solver, res.max_energy_error)


def test_random_nonseparable_polynomials_are_exact_or_raise():
    """A sweep over random quartic Hamiltonians and step sizes: HBVM(2s, s) conserves them
    exactly, so every run is exact to 1e-12 or raises a clean StepError; most succeed."""
    rng = np.random.default_rng(2026)
    ok = failed = 0
    for trial in range(24):
        s = 1 + trial % 2
        sys_ = Polynomial1D(rng.uniform(-0.3, 0.3, size=9))
        y0 = rng.uniform(-0.6, 0.6, size=2)
        h = rng.uniform(0.1, 0.9)
        try:
            res = integrate(HBVM(2 * s, s), sys_, y0, h, 100, sample_every=5, error_bound=None)
        except StepError:
            failed += 1
            continue
        assert res.max_energy_error <= 1e-12, (trial, h, res.max_energy_error)
        ok += 1
    assert ok >= 18, (ok, failed)


def test_coincident_bodies_raise_one_clean_error(capfd):
    """Two bodies at one position: a NonFiniteError on every path, nothing printed."""
    nb = NBody([1.0, 1e-3, 1e-3])
    y0 = np.zeros(18)
    y0[3] = y0[6] = 1.0          # bodies 1 and 2 both at x = 1
    y0[13] = y0[16] = 1.0
    for fast in (True, False):
        with pytest.raises(NonFiniteError, match=r"produced non-finite values.*coincident"):
            integrate(HBVM(6, 3), nb, y0, 0.01, 10, fast=fast)
    out, err = capfd.readouterr()
    assert "Exception ignored" not in err and "ZeroDivision" not in err


def _three_body():
    nb = NBody([1.0, 1e-3, 3e-4], G=1.0)
    x = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.6, 0.1]])
    v = np.array([[0.0, 0, 0], [0, 1.0, 0.05], [-0.78, 0, 0]])
    return nb, nb.state(x, v)


def test_every_separable_path_takes_the_same_steps():
    """Compiled engine, the same step run as Python, and HBVMIntegrator: the same states bit
    for bit and the same counters exactly (they run one step with one kernel)."""
    nb, y0 = _three_body()
    m, h, n = HBVM(8, 4), 0.05, 200
    fast = integrate(m, nb, y0, h, n, sample_every=n)
    slow = integrate(m, nb, y0, h, n, sample_every=n, fast=False)
    assert (fast.path, slow.path) == ("compiled-separable", "python-separable")
    assert np.array_equal(fast.y, slow.y)
    assert (fast.steps, fast.iterations, fast.nfev) == (slow.steps, slow.iterations, slow.nfev)
    from hbvm_md import HBVMIntegrator
    sim = nb.to_rebound(y0)
    drv = HBVMIntegrator(sim, s=4, k=8, dt=h, energy_tol=None)
    sim.steps(n)
    q = np.array([[p.x, p.y, p.z] for p in sim.particles]).ravel()
    assert np.array_equal(q, fast.y[-1, :9])
    assert (drv.nsteps, drv.niter, drv.nfev) == (fast.steps, fast.iterations, fast.nfev)
    # the full form of the same Hamiltonian: another iteration, the same solution to round-off
    full = integrate(m, nb, y0, h, n, sample_every=n, form="full")
    assert full.path == "python-full"
    assert np.max(np.abs(full.y[-1] - fast.y[-1])) <= 1e-12


def test_compiled_and_python_full_form_agree_exactly():
    from systems import Kepler, PoincareTransformed
    kep = Kepler(0.9)
    sys_ = PoincareTransformed.for_kepler(kep, alpha=1.0)
    assert isinstance(sys_, PoincareKepler)
    y0 = sys_.extend(kep.initial_state(), t=0.0)
    fast = integrate(HBVM(8, 4), sys_, y0, 0.05, 300, sample_every=300)
    slow = integrate(HBVM(8, 4), sys_, y0, 0.05, 300, sample_every=300, fast=False)
    assert (fast.path, slow.path) == ("compiled-full", "python-full")
    assert np.array_equal(fast.y, slow.y)
    assert (fast.iterations, fast.nfev) == (slow.iterations, slow.nfev)


def test_ase_path_runs_the_same_step():
    """HBVMDynamics with a gravity calculator (Python forces) against the compiled N-body
    engine on the same three bodies: the same solution to round-off."""
    from ase import Atoms
    from ase.calculators.calculator import Calculator, all_changes

    from hbvm_md import HBVMDynamics

    class Gravity(Calculator):
        implemented_properties = ["energy", "forces"]

        def __init__(self, masses):
            super().__init__()
            self.m = np.asarray(masses, dtype=float)

        def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
            super().calculate(atoms, properties, system_changes)
            x = self.atoms.positions
            f = np.zeros_like(x)
            e = 0.0
            for i in range(len(x)):
                for j in range(i + 1, len(x)):
                    d = x[j] - x[i]
                    r = np.sqrt(d @ d)
                    f[i] += self.m[i] * self.m[j] * d / r ** 3
                    f[j] -= self.m[i] * self.m[j] * d / r ** 3
                    e -= self.m[i] * self.m[j] / r
            self.results = {"energy": e, "forces": f}

    nb, y0 = _three_body()
    atoms = Atoms("H3", positions=y0[:9].reshape(3, 3), masses=nb.body_masses)
    atoms.set_momenta(y0[9:].reshape(3, 3))
    atoms.calc = Gravity(nb.body_masses)
    dyn = HBVMDynamics(atoms, 0.05, s=4, k=8)
    dyn.run(100)
    ref = integrate(HBVM(8, 4), nb, y0, 0.05, 100, sample_every=100)
    assert np.max(np.abs(atoms.positions.ravel() - ref.y[-1, :9])) <= 1e-12
    assert np.max(np.abs(atoms.get_momenta().ravel() - ref.y[-1, 9:])) <= 1e-12


def test_failed_integrate_keeps_the_samples_so_far():
    nb, y0 = _three_body()
    y0 = y0.copy()
    y0[12:15] = [0.0, 0.05e-3, 0.0]           # the planet nearly at rest: it falls onto the star
    with pytest.raises(StepError) as info:
        integrate(HBVM(6, 3), nb, y0, 0.05, 400, sample_every=4, energy_tol=1e-10)
    res = info.value.result
    assert res is not None and res.status == "failed" and res.message == str(info.value)
    assert 0 < res.steps < 400 and len(res.t) == res.steps // 4 + 1
    assert np.all(np.isfinite(res.y)) and res.t[-1] <= info.value.t


def test_unresolved_step_is_a_sibling_of_convergence_error():
    assert issubclass(UnresolvedStepError, StepError) and not issubclass(UnresolvedStepError, ConvergenceError)
    assert issubclass(NonFiniteError, ConvergenceError)
    import copy
    import pickle
    err = UnresolvedStepError(0.1, 2e-3, 1e-10, 5, t=3.0, hint="smaller")
    for clone in (copy.copy(err), pickle.loads(pickle.dumps(err))):
        assert type(clone) is UnresolvedStepError and str(clone) == str(err)
        assert (clone.h, clone.t, clone.change, clone.tolerance) == (0.1, 3.0, 2e-3, 1e-10)


def test_stepper_returns_copies_and_keeps_status():
    nb, y0 = _three_body()
    st = Stepper(HBVM(4, 2), nb, y0, solver="fixed_point")
    y1 = st.step(0.01)
    y1[:] = 1e9                                # the caller's array, not the state
    assert np.all(st.y < 1e3)
    st.y[:] = 1e9
    assert np.all(st.y < 1e3)
    assert st.status == "running"
    with pytest.raises(StepError):
        st.step(40.0)
    assert st.status == "failed" and st.nsteps == 1


def test_k_has_a_cap_with_a_reason():
    with pytest.raises(ValueError, match=r"`k` must be <= 128 \(got k=5000, s=2\).*double precision"):
        HBVM(5000, 2)
    with pytest.raises(ValueError, match=r"`k` must be <= 128"):
        HBVM.for_polynomial_degree(10000, 2)


def test_compiled_code_is_rebuilt_when_a_kernel_source_changes(tmp_path, monkeypatch):
    """The step module is named by a hash of its sources: editing the kernel's file gives a
    new module (a stale cache cannot be loaded), and the new force is the one used."""
    from integrators.specialise import specialise
    src = textwrap.dedent('''
        from integrators.jit import jit

        @jit
        def force(Q, params, out):
            for i in range(Q.shape[0]):
                out[i, 0] = -{K} * Q[i, 0]

        @jit
        def potential(q, params):
            return 0.5 * {K} * q[0] * q[0]
    ''')
    mod = tmp_path / "hbvm_test_kernel.py"
    mod.write_text(src.format(K="1.0"))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("HBVM_MD_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr("integrators.specialise._cache_dir", None)
    kern = importlib.import_module("hbvm_test_kernel")
    first = specialise(kern.force, kern.potential)
    name1 = first.run.py_func.__module__
    mod.write_text(src.format(K="4.0"))
    kern = importlib.reload(kern)
    second = specialise(kern.force, kern.potential)
    name2 = second.run.py_func.__module__
    assert name1 != name2 and name1.startswith("_hbvm_md_step_")
    assert (tmp_path / "cache" / f"{name2}.py").exists()

    class Spring(HamiltonianSystem):
        dim, masses = 1, np.ones(1)

        def potential(self, q):
            return 2.0 * np.asarray(q)[..., 0] ** 2

        def forces(self, q):
            return -4.0 * np.asarray(q)

        def energy(self, y):
            y = np.asarray(y)
            return 0.5 * y[..., 1] ** 2 + self.potential(y[..., :1])

        def gradient(self, y):
            return np.concatenate([-self.forces(np.asarray(y)[..., :1]), np.asarray(y)[..., 1:]], axis=-1)

        def separable_kernels(self):
            return kern.force, kern.potential, np.zeros(1)
    res = integrate(HBVM(2, 2), Spring(), [1.0, 0.0], np.pi / 40, 10)   # a quarter period of omega = 2
    assert abs(res.y[-1, 0]) < 1e-5 and res.max_energy_error < 1e-14   # cos(pi / 4) with K = 1


def test_no_writable_cache_folder_falls_back_with_one_warning(tmp_path, monkeypatch):
    import integrators.specialise as sp
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("HBVM_MD_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.setenv("HOME", str(blocker))
    monkeypatch.setattr(sp.numba.config, "CACHE_DIR", "")
    monkeypatch.setattr(sp, "_cache_dir", None)
    with pytest.warns(RuntimeWarning, match="no writable cache folder"):
        folder = sp.cache_dir()
    assert folder.is_dir() and os.access(folder, os.W_OK)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sp.cache_dir() == folder


def test_jit_without_a_cache_locator_compiles_in_memory(monkeypatch):
    import integrators.jit as jm
    real = jm.njit

    def njit(*args, **kwargs):
        if kwargs.get("cache"):
            raise RuntimeError("cannot cache function 'f': no locator available for file 'x'")
        return real(*args, **kwargs)
    monkeypatch.setattr(jm, "njit", njit)
    monkeypatch.setattr(jm, "_warned", False)

    def f(x):
        return 2.0 * x
    with pytest.warns(RuntimeWarning, match="cannot be cached on disk"):
        g = jm.jit(f)
    assert g(3.0) == 6.0


def test_everything_runs_with_numba_disabled():
    """NUMBA_DISABLE_JIT=1: the same step as plain Python, through the engine and REBOUND, with
    the same numbers to round-off."""
    code = textwrap.dedent('''
        import numpy as np
        from integrators import HBVM, integrate
        from systems import outer_solar_system
        from hbvm_md import HBVMIntegrator
        nb = outer_solar_system()
        r = integrate(HBVM(7, 6), nb, nb.initial_state(), 250.0, 4, sample_every=4)
        sim = nb.to_rebound()
        HBVMIntegrator(sim, s=6, k=7, dt=250.0)
        sim.steps(4)
        eq = nb.to_rebound()
        HBVMIntegrator(eq, s=2, k=8, dt=200.0, method="equip")   # alpha 1e-3: not Gauss's
        eq.steps(4)
        print(repr(r.y[-1].tolist()), r.path, sim.particles[1].x, eq.particles[1].x)
    ''')
    env = dict(os.environ, NUMBA_DISABLE_JIT="1", PYTHONPATH=ROOT)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    y_txt, path, x1, x1_equip = out.stdout.rsplit(" ", 3)
    nb = outer_solar_system()
    ref = integrate(HBVM(7, 6), nb, nb.initial_state(), 250.0, 4, sample_every=4)
    assert path == "python-separable"
    assert np.max(np.abs(np.array(eval(y_txt)) - ref.y[-1])) <= 1e-12
    assert abs(float(x1) - ref.y[-1, 3]) <= 1e-12
    # EQUIP through REBOUND as Python (the host's views of its packed arrays and eref)
    ref = integrate(EQUIP(8, 2), nb, nb.initial_state(), 200.0, 4, sample_every=4)
    assert abs(float(x1_equip) - ref.y[-1, 3]) <= 1e-12


def test_column_innermost_sums_give_the_narrow_numbers_bit_for_bit():
    """The stage values, projections and initial guesses are summed column-innermost
    (vectorised) from NARROW columns on and entry by entry below; both orders must give the same
    numbers, nan and inf included, or a scene would change its answer with its number of
    bodies."""
    from integrators import core
    rng = np.random.default_rng(7)
    for trial in range(60):
        n = int(rng.integers(1, 12))
        s = int(rng.integers(1, min(n, 8) + 1))
        m = int(rng.integers(1, 40))
        sc = 10.0 ** rng.uniform(-5, 5, size=m)
        y = rng.normal(size=2 * m) * np.tile(sc, 2)
        cy = y * 1e-17 * rng.normal(size=2 * m)
        minv = rng.uniform(0.1, 10, m)
        g = rng.normal(size=(s, m)) * sc
        C2 = rng.normal(size=(n, s))
        C2_lo = C2 * 1e-17 * rng.normal(size=(n, s))
        ht = rng.normal(size=n)
        R = np.full((5, 2 * m), np.nan)        # scratch: its contents must not matter
        a = np.empty((s, m))
        Q1, Q2 = np.empty((n, m)), np.empty((n, m))
        exact = trial % 2 == 0        # with the low parts (the step's last evaluation) or not
        sc_ = StepConstants(np.nan, ht, ht * 1e-17, 0.3, 1e-18)
        core.stage_positions(y, cy, minv, g, C2, C2_lo, sc_, a, Q1, R, exact)
        core.stage_positions_narrow(y, cy, minv, g, C2, C2_lo, sc_, a, Q2, exact)
        assert np.array_equal(Q1, Q2)
        W = rng.normal(size=(s, n))
        F = rng.normal(size=(n, m)) * sc
        if trial % 3 == 1:
            F[rng.integers(n), rng.integers(m)] = [np.nan, np.inf, -np.inf][trial % 9 // 3]
        g1 = rng.normal(size=(s, m))
        g2 = g1.copy()
        g0 = g1.copy()
        r1 = core.project(W, F, g1, R)
        r2 = core.project_narrow(W, F, g2)
        assert np.array_equal(g1, g2, equal_nan=True)
        assert np.array_equal(np.array(r1), np.array(r2), equal_nan=True), (r1, r2)
        # each column's maxima kept (the followers' own stop rules): the same g and maxima
        g3, dc, sc = g0.copy(), np.empty(m), np.empty(m)
        core.project_each(W, F, g3, R, dc, sc)
        assert np.array_equal(g3, g1, equal_nan=True)
        assert np.array_equal(dc, np.max(np.abs(g1 - g0), axis=0), equal_nan=True)
        assert np.array_equal(sc, np.max(np.where(np.isnan(g1), 0.0, np.abs(g1)), axis=0))
        E = rng.normal(size=(s, s))
        G1, G2 = np.empty((s, m)), np.empty((s, m))
        core.guess(E, F[:s] if n >= s else g, G1)
        core.guess_narrow(E, F[:s] if n >= s else g, G2)
        assert np.array_equal(G1, G2, equal_nan=True)
        gg = rng.normal(size=(s, 2 * m))
        Y1, Y2 = np.empty((n, 2 * m)), np.empty((n, 2 * m))
        core.full_stages(y, cy, gg, C2, C2_lo, 0.7, Y1, R, exact)
        core.full_stages_narrow(y, cy, gg, C2, C2_lo, 0.7, Y2, exact)
        assert np.array_equal(Y1, Y2)


def test_numba_function_ids_start_at_a_random_offset_in_every_process():
    """Cached code from two processes must not share symbol names (see integrators.jit._Ids):
    the project's compilations draw ids from a counter that starts above 2^40, at a different
    place in each process (numba's own counter is left alone: tests/test_compile.py)."""
    code = ("import integrators.jit\n"
            "print(next(integrators.jit._Ids.counter))\n")
    ids = [int(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout) for _ in range(2)]
    assert min(ids) > 2 ** 40 and ids[0] != ids[1]


def test_fused_two_product_gives_dekkers_numbers():
    """Compiled, two_product takes its error term from one fused multiply-add; as Python it is
    Dekker's product: both exact, so the same numbers over the normal range (and a product
    rounded differently, or an error term off by an ulp, would fail here)."""
    import numba

    from integrators import core

    @numba.njit
    def fused(a, b, hi, lo):
        for i in range(a.shape[0]):
            hi[i], lo[i] = core.two_product(a[i], b[i])

    rng = np.random.default_rng(7)
    n = 20000
    a = rng.standard_normal(n) * 10.0 ** rng.integers(-100, 100, n)
    b = rng.standard_normal(n) * 10.0 ** rng.integers(-100, 100, n)
    a[:4] = [0.0, -0.0, 1.0, 3.0]
    hi, lo = np.empty(n), np.empty(n)
    fused(a, b, hi, lo)
    ref = np.array([core.two_product(float(x), float(y)) for x, y in zip(a, b)])
    assert np.array_equal(hi, ref[:, 0]) and np.array_equal(lo, ref[:, 1])
    assert np.count_nonzero(lo) > n // 2       # the error terms are there to compare


def test_carved_work_arrays_tile_their_buffers_and_a_short_buffer_is_refused():
    """core.carve views the work buffers without slices (integrators.pointers.view): every view
    lies inside its buffer, no two overlap, each has its shape, and a buffer shorter than
    core.work_sizes is an error rather than views past its end."""
    from integrators import core

    n, s, u, m, d = 7, 6, 18, 18, 36
    nf, nc = core.work_sizes(n, s, u, m, d)
    work, cwork = np.zeros(nf), np.zeros(nc, dtype=complex)
    views = core.carve(work, cwork, n, s, u, m, d)
    shapes = [(n,), (n,), (5,), (m,), (m,), (s, u), (s, u), (s, u), (n, u), (n, u), (n, u),
              (n, u), (n, u), (d,), (d,), (5, min(u, core.BLOCK)), (s, u), (s, u)]
    assert [v.shape for v in views] == shapes
    spans = {0: [], 1: []}
    for v in views:
        buf = cwork if v.dtype == complex else work
        start = v.ctypes.data - buf.ctypes.data
        assert v.flags.c_contiguous and 0 <= start and start + v.nbytes <= buf.nbytes
        spans[v.dtype == complex].append((start, start + v.nbytes))
    for group in spans.values():
        group.sort()
        assert all(e0 <= s1 for (s0, e0), (s1, e1) in zip(group, group[1:]))
    for v in views:                      # writes land in the buffers
        v[...] = 1.0
    assert work.sum() == sum(v.size for v in views if v.dtype != complex)
    with pytest.raises(ValueError, match="work_sizes"):
        core.carve(work[:-1], cwork, n, s, u, m, d)


def _stop_sequence(deltas, scale=1.0, floor=0.0, hstate=np.inf, F=None, tol=0.0):
    """core.stop_action over a sequence of increments as the step's loop calls it: the actions
    until the first that is not ITERATE, and the iteration it came at."""
    from integrators import core

    hist = np.array([np.inf, 0.0, np.inf, np.inf, np.nan])
    F = np.zeros((2, 3)) if F is None else F
    for it, d in enumerate(deltas, 1):
        a = core.stop_action(d, scale, F, floor, hstate, scale, 1.0, it, hist, tol)
        if a != core.ITERATE:
            return a, it
    return core.ITERATE, len(deltas)


def test_a_tolerance_stops_at_the_error_estimated_from_the_contraction():
    """stop_action with tol > 0 (HBVMDynamics' 1e-12 for a calculator that is not a
    polynomial): the increments of EMT copper, HBVM(3, 2) at 5 fs (relative to the
    coefficients), polish at 2e-11, whose estimated error theta delta (theta = 6.7e-3, the
    larger of the last two ratios) is below 1e-12, one iteration before the increment itself
    is; without a tolerance the same increments iterate to the stall.  A single ratio is no
    contraction estimate, and a contraction weaker than TOL_CONTRACTION takes no exit."""
    from integrators import core

    emt = [2.4e-2, 1.3e-4, 3.3e-7, 3.4e-9, 2.2e-11, 5.8e-14, 6.4e-15, 1.9e-15, 1.9e-15]
    assert _stop_sequence(emt, tol=1e-12) == (core.POLISH, 5)
    assert _stop_sequence(emt, floor=8e-14) == (core.POLISH, 9)           # the round-off rule
    # only one ratio known at the second increment (1e-7: theta delta 1e-14), however small:
    # iterate; at the fourth, theta = 1e-2 from two ratios and theta delta = 1e-13
    assert _stop_sequence([1.0, 1e-7, 1e-9, 1e-11], tol=1e-12) == (core.POLISH, 4)
    # theta = 0.5 > TOL_CONTRACTION: the error estimate is not trusted, the increment decides
    slow = [0.5 ** j * 1e-10 for j in range(12)]
    assert _stop_sequence(slow, tol=1e-12) == (core.POLISH, 8)            # 7.8e-13 <= 1e-12


def test_a_strong_contraction_polishes_at_round_off_without_waiting_for_the_stall():
    """stop_action: increments of a soft-sphere fluid (ratios 3e-5, 1.4e-5, then the max norm of
    1e5 atoms' round-off, 60 ulps of the coefficients) polish at that round-off increment; the
    stall rule alone waited two more iterations.  A weaker contraction (ratio 1e-2, planets and
    Kepler) or an increment above every round-off level still iterates, and a stall at
    round-off still polishes."""
    from integrators import core

    fluid = [8e-3, 2.4e-7, 3.3e-12, 1.3e-14, 1.4e-15, 1.4e-15]
    assert _stop_sequence(fluid, floor=5e-13) == (core.POLISH, 4)
    assert _stop_sequence(fluid, hstate=0.5) == (core.POLISH, 4)          # the state level
    assert _stop_sequence(fluid) == (core.POLISH, 4)                      # 64 ulps of scale
    assert _stop_sequence(fluid, scale=0.1) == (core.POLISH, 6)           # 1.3e-14 > 64 ulps of 0.1: the stall
    weak = [1e-6, 1e-8, 1e-10, 1e-12, 1e-14, 1e-15, 1e-15]                # ratio 1e-2
    assert _stop_sequence(weak, floor=5e-13) == (core.POLISH, 7)
    # the contraction is strong but the last ratio before the stop is not: theta is the larger
    assert _stop_sequence([1e-3, 1e-8, 1e-10, 1e-14, 1e-15, 1e-15]) == (core.POLISH, 6)
    # strong, at the state's round-off, but theta^2 delta_prev (1e-18) above 1e-3 ulp of scale
    assert _stop_sequence([1e-1, 1e-5, 1e-9, 1e-15, 1e-15], hstate=1.0) == (core.POLISH, 5)
    # strong, but the increments stop above every round-off level: never accepted
    assert _stop_sequence([1e-3, 1e-8, 1e-13, 5e-14, 4e-14, 4e-14, 4e-14]) == (-core.DIVERGED, 7)


@pytest.mark.parametrize("narrow", [False, True])
def test_full_stages_keep_the_coefficients_low_parts_on_average(narrow):
    """The full form's stages with the low parts (the polish's) must carry h I_lo gamma on
    average: left to the rounded sum it was rounded away, the same way on every step (a stage
    error of exactly -h I_lo gamma plus round-off), and the energy of a polynomial H drifted
    (tests/test_conservation.py).  Regression of the stage error Y - S on h I_lo gamma, S
    computed exactly (fractions) over random states: slope -1 before the fix, 0 after."""
    from fractions import Fraction

    from integrators import core
    m_ = HBVM(12, 6)
    I, I_lo = np.ascontiguousarray(m_.I), np.ascontiguousarray(m_.I_lo)
    n, s = I.shape
    rng = np.random.default_rng(7)
    u, h = 120, 0.5
    y = rng.uniform(0.1, 0.3, u) * rng.choice([-1.0, 1.0], u)
    cy = (rng.uniform(-0.5, 0.5, u) * np.spacing(np.abs(y)))    # the state's low part
    g = np.empty((s, u))
    g[0] = rng.uniform(-0.3, 0.3, u)
    for l in range(1, s):
        g[l] = g[0] * rng.uniform(-0.3, 0.3, u) * h ** l
    Y = np.empty((n, u))
    if narrow:
        core.full_stages_narrow(y, cy, g, I, I_lo, h, Y, True)
    else:
        core.full_stages(y, cy, g, I, I_lo, h, Y, np.empty((5, u)), True)
    err, lo = [], []
    for i in range(n):
        for j in range(u):
            S = Fraction(y[j]) - Fraction(cy[j]) + Fraction(h) * sum(
                (Fraction(I[i, l]) + Fraction(I_lo[i, l])) * Fraction(g[l, j]) for l in range(s))
            err.append(float(Fraction(Y[i, j]) - S))
            lo.append(h * float(sum(Fraction(I_lo[i, l]) * Fraction(g[l, j]) for l in range(s))))
    err, lo = np.array(err), np.array(lo)
    slope = float(np.dot(err, lo) / np.dot(lo, lo))
    assert abs(slope) < 0.3, slope
