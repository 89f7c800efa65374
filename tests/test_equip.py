"""EQUIP(k, s): the tableau (symplectic for every alpha, Gauss at alpha = 0), energy and
angular momentum both at round-off on Kepler, order 2s against the exact flow, a quadratic
invariant other than angular momentum, polynomial energy exact, and ASE with method="equip"."""
import numpy as np
import pytest

from integrators import EQUIP, HBVM, ConvergenceError, Stepper, integrate
from systems import FPU
from systems.base import SeparableSystem
from systems.kepler import Kepler

KEPLER = Kepler(0.6)
H_KEPLER = 2 * np.pi / 100


def _angular_momentum(y):
    return y[..., 0] * y[..., 3] - y[..., 1] * y[..., 2]


def _perturbed_starts(n, scale=1e-3, seed=1):
    y0 = KEPLER.initial_state()
    rng = np.random.default_rng(seed)
    return [y0 * (1 + scale * rng.standard_normal(4)) for _ in range(n)]


# -- the tableau ---------------------------------------------------------------------------
@pytest.mark.parametrize("s", [2, 3, 4, 6])
def test_symplectic_for_every_alpha_and_gauss_at_zero(s):
    m = EQUIP(s + 2, s)
    gauss = HBVM(s, s)
    A0, b, c = m.butcher_tableau()
    Ag, bg, cg = gauss.butcher_tableau()
    assert np.array_equal(A0, Ag) and np.array_equal(b, bg) and np.array_equal(c, cg)
    for alpha in (1e-8, 0.1, -0.25):
        assert m.symplecticity_defect(alpha) <= 1e-15
        A, _, _ = m.butcher_tableau(alpha)
        assert np.max(np.abs(A - A0)) > 1e-3 * abs(alpha)      # the perturbation is there
    # HBVM(k > s, s) is not symplectic: the check can fail
    assert HBVM(s + 2, s).symplecticity_defect() > 1e-3


def test_equip_data_and_errors():
    m = EQUIP(6, 2)
    assert (m.order, m.polynomial_degree_exact, m.quadrature_degree) == (4, 6, 11)
    assert m.n_stages == 2 and m.tau_path.shape == (6,)
    assert repr(m) == "EQUIP(6, 2)" and m == EQUIP(6, 2) and m != HBVM(6, 2)
    assert hash(m) != hash(HBVM(6, 2))
    with pytest.raises(ValueError, match=r"`s` must be >= 2 for EQUIP \(got s=1\)"):
        EQUIP(3, 1)
    with pytest.raises(ValueError, match=r"`k` must be >= `s` \(got k=2, s=3\)"):
        EQUIP(2, 3)
    with pytest.raises(AttributeError, match="immutable"):
        m.k = 7


class _Linear(SeparableSystem):
    """Two coupled oscillators, H = p^T p / 2 + q^T K q / 2 (quadratic)."""

    dim = 2
    masses = np.ones(2)
    K = np.array([[2.0, 0.5], [0.5, 1.0]])

    def potential(self, q):
        q = np.asarray(q, dtype=float)
        return 0.5 * np.einsum("...i,ij,...j->...", q, self.K, q)

    def forces(self, q):
        return -np.asarray(q, dtype=float) @ self.K


def test_alpha_zero_is_gauss_where_gauss_already_conserves():
    """On a linear system (quadratic H) Gauss conserves H: the energy condition holds at
    alpha = 0 and EQUIP's steps are Gauss's."""
    sys_ = _Linear()
    y0 = np.array([1.0, 0.3, -0.2, 0.5])
    a = integrate(EQUIP(4, 2), sys_, y0, 0.1, 200, sample_every=200, fast=False)
    b = integrate(HBVM(2, 2), sys_, y0, 0.1, 200, sample_every=200, fast=False)
    assert np.max(np.abs(a.y[-1] - b.y[-1])) <= 1e-14


# -- conservation --------------------------------------------------------------------------
@pytest.mark.parametrize("k, s", [(6, 2), (12, 4)])
def test_kepler_energy_and_angular_momentum_both_at_round_off(k, s):
    """The issue's figure: Kepler e = 0.6, h = 2 pi / 100, 1e4 steps; HBVM(6, 2) loses the
    angular momentum (5e-6) and Gauss the energy (2e-5), EQUIP keeps both (medians over
    five perturbed starts)."""
    dE, dL = [], []
    for y0 in _perturbed_starts(5):
        r = integrate(EQUIP(k, s), KEPLER, y0, H_KEPLER, 10_000, sample_every=50)
        L = _angular_momentum(r.y)
        dE.append(r.max_energy_error)
        dL.append(np.max(np.abs(L - L[0])) / abs(L[0]))
    assert np.median(dE) <= 1e-14, dE
    assert np.median(dL) <= 1e-14, dL


def test_hbvm_loses_the_angular_momentum_that_equip_keeps():
    y0 = KEPLER.initial_state()
    r = integrate(HBVM(6, 2), KEPLER, y0, H_KEPLER, 2000, sample_every=50)
    L = _angular_momentum(r.y)
    assert np.max(np.abs(L - L[0])) / abs(L[0]) > 1e-9


@pytest.mark.parametrize("k, s", [(6, 2), (9, 3)])
def test_order_2s_against_the_exact_flow(k, s):
    y0 = KEPLER.initial_state()
    T = 2 * np.pi
    ns = [40, 56, 80, 113] if s == 2 else [40, 50, 63, 80]
    errs = []
    for n in ns:
        h = T / n
        r = integrate(EQUIP(k, s), KEPLER, y0, h, n, sample_every=n)
        exact = KEPLER.exact_solution(y0, np.longdouble(n) * h)
        errs.append(float(np.max(np.abs(r.y[-1] - exact))))
    errs = np.array(errs)
    keep = errs > 1e-12                     # off the round-off plateau
    assert keep.sum() >= 3, errs
    slope = -np.polyfit(np.log(np.array(ns)[keep]), np.log(errs[keep]), 1)[0]
    assert abs(slope - 2 * s) <= 0.3, (slope, errs)


def test_fpu_quartic_energy_exact():
    """FPU's stiff chain (quartic H, omega = 50, h omega = 1/2): EQUIP(8, 4) conserves H
    exactly (k >= nu s / 2 = 8) where Gauss (the same stages, alpha = 0) does not."""
    fpu = FPU(3, 50.0)
    y0 = fpu.initial_state()
    r = integrate(EQUIP(8, 4), fpu, y0, 0.01, 1000, sample_every=50)
    g = integrate(HBVM(4, 4), fpu, y0, 0.01, 1000, sample_every=50)
    assert r.max_energy_error <= 1e-13
    assert g.max_energy_error > 10 * r.max_energy_error


def test_fpu_s2():
    """FPU's stiff chain with s = 2 (issue 35, item 5): dE/dalpha (leading term -xi_1^2 h^3
    H'''(f, f, f)) changes sign along the trajectory, and the secant with the last step's slope
    left |alpha| <= 0.25 (a ConvergenceError before the fix); the root is small (|alpha| <=
    0.034 over the run) and the step now measures its own slope and finds it."""
    fpu = FPU(3, 50.0)
    r = integrate(EQUIP(4, 2), fpu, fpu.initial_state(), 0.001, 2000, sample_every=100)
    assert r.max_energy_error <= 1e-13


# -- the energy condition's root search (integrators.equip_core.update_alpha) ----------------
def _solve_alpha(E_of, alpha_last, slope_last, scale=1e-3):
    """update_alpha driven by a given E(alpha), as the step drives it: (answer, alpha, updates)."""
    from integrators import equip_core as ec
    es = np.zeros(ec.ES)
    ec.start(es, np.array([np.nan, alpha_last, slope_last]))
    while True:
        answer = ec.update_alpha(es, E_of(es[0]), scale, 0.0)
        if answer != ec.UPDATED:
            return answer, es[0], int(es[4])


def test_root_search_with_a_stale_slope_of_the_wrong_sign():
    """ASE's copper nanoparticle at t = 205 fs (43 atoms, 5 fs, s = 2), E(alpha) as measured
    there (E = g0 + a (alpha + alpha^2 / 2), exact for s = 2 at order h^3): the last step's
    root was alpha = -0.07 with slope -2.5e-6, this step's slope is +6.5e-6 and its root +0.031.
    The secant with the stale slope jumped to alpha < -0.25 and the step failed; the step
    measures its own slope first, and converges to the root."""
    from integrators import equip_core as ec
    E_of = lambda a: -2.0e-7 + 6.5e-6 * (a + 0.5 * a * a)       # noqa: E731
    answer, alpha, updates = _solve_alpha(E_of, -0.07, -2.5e-6)
    assert answer in (ec.CONVERGED, ec.REITERATE), answer
    root = (-6.5e-6 + np.sqrt(6.5e-6 ** 2 + 4 * 3.25e-6 * 2.0e-7)) / 6.5e-6
    assert abs(alpha - root) <= 1e-12 and updates <= 6, (alpha, root, updates)


def test_root_search_beyond_the_secant_range():
    """No root with |alpha| <= 0.25 (ALPHA_MAX), one at -0.4 (E a function of (1 + alpha)^2,
    as for s = 2): the fresh secant leaves the range, the scan brackets the root closest to
    the start and regula falsi finds it."""
    from integrators import equip_core as ec
    E_of = lambda a: 9.4e-8 + 9.4e-8 / 0.64 * ((1 + a) ** 2 - 1)      # noqa: E731
    answer, alpha, updates = _solve_alpha(E_of, 1e-3, 2.9e-7)
    assert answer in (ec.CONVERGED, ec.REITERATE), answer
    assert abs(alpha + 0.4) <= 1e-9 and updates <= ec.MAX_UPDATES + ec.FALLBACK_UPDATES


def test_root_search_without_a_root_fails():
    """E(alpha) < 0 for every alpha (the 19-atom copper cluster at t = 0, seed 2, 5 fs): the
    search fails (never a converged alpha that is not a root) within its budget."""
    from integrators import equip_core as ec
    E_of = lambda a: -4.7e-8 + 1.6e-7 * a - 5.0e-7 * a * a        # max -3.4e-8 at 0.16
    answer, alpha, updates = _solve_alpha(E_of, np.nan, np.nan)
    assert answer == ec.FAILED
    assert updates <= ec.MAX_UPDATES + ec.FALLBACK_UPDATES


def _copper19(seed):
    from ase.calculators.emt import EMT
    from ase.cluster.cubic import FaceCenteredCubic
    from hbvm_md.reports.md_comparison import maxwell_boltzmann
    atoms = FaceCenteredCubic("Cu", [(1, 0, 0), (1, 1, 0), (1, 1, 1)], [2, 2, 2],
                              latticeconstant=3.61)
    maxwell_boltzmann(atoms, 300.0, seed)
    atoms.calc = EMT()
    return atoms


def test_ase_copper_cluster_where_the_secant_failed():
    """19 EMT copper atoms (ASE's tutorial cluster, smaller), 5 fs, s = 2, seed 3: before the
    root search the step at t = 75 fs failed ("did not converge", increment at round-off);
    now the steps past it keep the energy to 1e-9 eV/atom and the angular momentum to
    round-off."""
    from ase import units
    from hbvm_md import HBVMDynamics
    atoms = _copper19(3)
    dyn = HBVMDynamics(atoms, 5 * units.fs, method="equip")
    E, L = [], []

    def observe():
        E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy())
        L.append(np.cross(atoms.get_positions(), atoms.get_momenta()).sum(axis=0))
    dyn.attach(observe)
    dyn.run(18)
    L = np.array(L)
    scale = np.sum(np.linalg.norm(atoms.get_positions(), axis=1)
                   * np.linalg.norm(atoms.get_momenta(), axis=1))
    assert np.ptp(E) / len(atoms) <= 1e-9, np.ptp(E)
    assert np.max(np.linalg.norm(L - L[0], axis=1)) / scale <= 1e-14


def test_ase_copper_cluster_without_a_root_says_equip():
    """Where no alpha conserves the energy (19 copper atoms at t = 0, seed 2, 5 fs, s = 2:
    E(alpha) < 0 for every alpha) the step fails loudly, names EQUIP and the energy
    condition, and leaves the atoms as they were."""
    from ase import units
    from hbvm_md import HBVMDynamics
    from integrators import EnergyConditionError
    atoms = _copper19(2)
    q, p = atoms.get_positions(), atoms.get_momenta()
    dyn = HBVMDynamics(atoms, 5 * units.fs, method="equip")
    with pytest.raises(EnergyConditionError, match=r"^EQUIP step of size h=5 fs at t=0 fs did "
                                                   r"not converge: no alpha .* conserves the "
                                                   r"energy .*use a smaller timestep"):
        dyn.run(1)
    assert np.array_equal(atoms.get_positions(), q) and np.array_equal(atoms.get_momenta(), p)


def test_step_errors_name_the_method():
    from integrators.core import DIVERGED, N_COUNTERS
    from integrators.equip_core import NO_ENERGY_ROOT
    from integrators.errors import EnergyConditionError, step_error
    c = np.zeros(N_COUNTERS)
    assert str(step_error(DIVERGED, 0.1, 2.0, c, "newton")).startswith("HBVM step of size h=0.1")
    err = step_error(DIVERGED, 0.1, 2.0, c, "newton", method="EQUIP")
    assert str(err).startswith("EQUIP step of size h=0.1 at t=2 did not converge: newton")
    for method in ("EQUIP", None):      # (None: a host that does not name the method)
        err = step_error(NO_ENERGY_ROOT, 0.1, None, c, "fixed_point", method=method)
        assert isinstance(err, EnergyConditionError) and isinstance(err, ConvergenceError)
        assert str(err).startswith("EQUIP step of size h=0.1 did not converge: no alpha")


class _CoupledOscillators(SeparableSystem):
    """H = p^T p / 2 + q^T K q / 2 + (q1^2 + q2^2)^2 / 4: the quartic term is rotation
    invariant in the (q1, q2) plane when K is, so L12 = q1 p2 - q2 p1 is conserved: a
    quadratic invariant of a nonlinear system, which HBVM(k > s) does not keep."""

    dim = 2
    masses = np.ones(2)

    def potential(self, q):
        q = np.asarray(q, dtype=float)
        r2 = np.sum(q * q, axis=-1)
        return 0.5 * r2 + 0.25 * r2 ** 2

    def forces(self, q):
        q = np.asarray(q, dtype=float)
        r2 = np.sum(q * q, axis=-1, keepdims=True)
        return -(1.0 + r2) * q


def test_quadratic_invariant_of_a_nonlinear_system_kept():
    sys_ = _CoupledOscillators()
    y0 = np.array([1.0, 0.2, -0.3, 0.9])
    inv = lambda y: y[..., 0] * y[..., 3] - y[..., 1] * y[..., 2]       # noqa: E731
    e = integrate(EQUIP(4, 2), sys_, y0, 0.1, 500, sample_every=10, fast=False)
    h = integrate(HBVM(4, 2), sys_, y0, 0.1, 500, sample_every=10, fast=False)
    de = np.max(np.abs(inv(e.y) - inv(y0)))
    dh = np.max(np.abs(inv(h.y) - inv(y0)))
    assert de <= 1e-14 and e.max_energy_error <= 1e-14, (de, e.max_energy_error)
    assert dh > 1e-9                      # HBVM keeps the energy, not this invariant


@pytest.mark.parametrize("solver", ["fixed_point", "newton"])
def test_both_solvers_and_full_form(solver):
    y0 = KEPLER.initial_state()
    for form in ("separable", "full"):
        r = integrate(EQUIP(6, 2), KEPLER, y0, H_KEPLER, 300, sample_every=10, solver=solver,
                      form=form)
        L = _angular_momentum(r.y)
        assert r.max_energy_error <= 2e-14 and np.max(np.abs(L - L[0])) <= 2e-14
        if solver == "newton":
            assert r.newton_steps == 300


def test_stepper_adaptive_and_failure_leaves_state():
    y0 = KEPLER.initial_state()
    r = integrate(EQUIP(8, 3), KEPLER, y0, 0.05, adaptive=True, t_end=20.0, epsilon=1e-12)
    L = _angular_momentum(r.y)
    assert r.t[-1] == 20.0
    assert r.max_energy_error <= 1e-14 and np.max(np.abs(L - L[0])) / abs(L[0]) <= 1e-14
    st = Stepper(EQUIP(6, 2), KEPLER, y0, solver="fixed_point", max_iter=3)
    y_before = st.y.copy()
    with pytest.raises(Exception, match="did not converge|converge"):
        st.step(H_KEPLER)
    assert np.array_equal(st.y, y_before) and st.t == 0.0 and st.nsteps == 0


# -- ASE -----------------------------------------------------------------------------------
def test_ase_free_cluster_energy_and_angular_momentum_at_round_off():
    from ase import units
    from hbvm_md import HBVMDynamics
    from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann

    def run(method):
        atoms, _ = default_cluster(13)
        maxwell_boltzmann(atoms, 300.0, 3)
        p = atoms.get_momenta()
        r = atoms.get_positions()
        # a spin about the centre of mass, so that the angular momentum has a scale
        w = np.array([0.0, 0.0, 0.02])
        p += atoms.get_masses()[:, None] * np.cross(w, r - atoms.get_center_of_mass())
        atoms.set_momenta(p)
        dyn = HBVMDynamics(atoms, 5 * units.fs, method=method)
        E, L = [], []

        def observe():
            E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy())
            L.append(np.cross(atoms.get_positions(), atoms.get_momenta()).sum(axis=0))
        dyn.attach(observe)
        dyn.run(200)
        E, L = np.array(E), np.array(L)
        return (np.max(np.abs(E - E[0])) / abs(E[0]),
                np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]), dyn)

    dE, dL, dyn = run("equip")
    assert repr(dyn.method).startswith("EQUIP(") and dyn.todict()["method"] == repr(dyn.method)
    assert dE <= 1e-13 and dL <= 1e-13, (dE, dL)


def test_ase_method_argument_checked():
    from ase import units
    from hbvm_md import HBVMDynamics
    from hbvm_md.reports.md_comparison import default_cluster
    atoms, _ = default_cluster(13)
    with pytest.raises(ValueError, match=r"`method` must be one of \('hbvm', 'equip'\) "
                                         r"\(got method='gauss'\)"):
        HBVMDynamics(atoms, units.fs, method="gauss")
    with pytest.raises(ValueError, match=r"`nodes` must be 'gauss' with method='equip'"):
        HBVMDynamics(atoms, units.fs, method="equip", nodes="lobatto")


def test_outer_solar_system_energy_and_angular_momentum():
    """The engine path with many columns (the blocked sums): EQUIP(9, 8) at 500 days keeps
    the energy and the total angular momentum at round-off (HBVM(9, 8) keeps the energy)."""
    from systems.solar import outer_solar_system
    S = outer_solar_system()
    y0 = S.initial_state()
    r = integrate(EQUIP(9, 8), S, y0, 500.0, 400, sample_every=20)
    L = np.array([S.angular_momentum(y) for y in r.y])
    assert r.max_energy_error <= 1e-14
    assert np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]) <= 1e-14


def test_for_polynomial_degree_uses_hbvms_rule():
    # the energy condition's k-point rule is HBVM(k, s)'s: exact for degree nu when k >= nu s / 2
    assert EQUIP.for_polynomial_degree(4, 4).k == 8
    assert EQUIP.for_polynomial_degree(3, 3).k == 5
    assert EQUIP.for_polynomial_degree(1, 2).k == 2
    with pytest.raises(ValueError, match="`nodes` must be 'gauss' for EQUIP"):
        EQUIP.for_polynomial_degree(4, 2, nodes="lobatto")


def test_rebound_defaults_per_method():
    """Through REBOUND each method has its own adaptive defaults: EQUIP s = 8 at epsilon =
    1e-17 (integrators.equip.DEFAULT_S, DEFAULT_EPSILON), HBVM s = 6 at 3e-15; what the user
    gives is kept."""
    pytest.importorskip("rebound")
    from hbvm_md import HBVMIntegrator
    from integrators.engine import DEFAULT_EPSILON
    from systems.solar import outer_solar_system
    S = outer_solar_system()
    sim = S.to_rebound()
    assert HBVMIntegrator(sim, method="equip").method == EQUIP(9, 8)
    assert sim.integrator.epsilon == 1e-17
    sim = S.to_rebound()
    assert HBVMIntegrator(sim).method.s == 6 and sim.integrator.epsilon == DEFAULT_EPSILON
    sim = S.to_rebound()
    assert HBVMIntegrator(sim, method="equip", s=6, epsilon=1e-3).method.s == 6
    assert sim.integrator.epsilon == 1e-3
