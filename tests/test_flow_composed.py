"""HBVM composed with the Keplerian flows (systems.flow_composed, issue 48): the transformed
system run by the one step, its recentring hook, its order, its agreement with plain HBVM and
the step's own error estimate through a close encounter."""
import numpy as np
import pytest

from integrators import HBVM, Stepper, UnresolvedStepError, integrate
from integrators.kepler_flow import kepler_step_stm, kepler_step_vjp, orbit_state
from systems import NBody
from systems.base import SeparableSystem
from systems.flow_composed import FlowComposed


def two_planets(f=1e-2):
    """A star and two planets (G = 1): a = 1, e = 0.1 and a = 1.6, e = 0.05, inclined;
    masses f and f / 2."""
    x = np.array([[0, 0, 0], [0.9, 0, 0], [-1.68, 0, 0.05]])
    v = np.array([[0, 0, 0], [0, np.sqrt(1.9 / 0.9), 0], [0, -np.sqrt(2 / 1.68 - 1 / 1.6), 0]])
    return NBody([1.0, f, f / 2], 1.0, positions=x, velocities=v)


def composed(nb, s, k, h, n, **kw):
    fc = FlowComposed.from_nbody(nb, h)
    r = integrate(HBVM(k, s), fc, fc.extend(nb.initial_state()), h, n, sample_every=n,
                  form="full", **kw)
    return fc, r


def plain_reference(nb, T, n=4000):
    return integrate(HBVM(12, 8), nb, nb.initial_state(), T / n, n, sample_every=n).y[-1]


def _assert_gradient_of_energy(fc, Y):
    """The kernel's gradient is the derivative of H~ (central differences, 1e-7)."""
    g = fc.gradient(Y)[0]
    for j in range(Y.size):
        e = 1e-6
        Yp, Ym = Y.copy(), Y.copy()
        Yp[j] += e
        Ym[j] -= e
        fd = (fc.energy(Yp) - fc.energy(Ym)) / (2 * e)
        assert abs(g[j] - fd) <= 1e-7 * max(1.0, abs(g[j])), j


def test_pullback_is_the_transposed_stm():
    rng = np.random.default_rng(3)
    for e in (0.0, 0.5, 0.99, 3.0):
        x, v = (np.asarray(a, dtype=float) for a in orbit_state(e, 1.3))
        for dt in (-4.0, 0.0, 0.9, 25.0):
            x1, v1, phi = np.empty(3), np.empty(3), np.empty((6, 6))
            kepler_step_stm(x, v, 1.0, dt, x1, v1, phi)
            g = rng.standard_normal(6)
            x2, v2, wx, wv = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
            kepler_step_vjp(x, v, 1.0, dt, g[:3].copy(), g[3:].copy(), x2, v2, wx, wv)
            assert np.array_equal(x1, x2) and np.array_equal(v1, v2)
            assert np.abs(np.r_[wx, wv] - phi.T @ g).max() <= 1e-13 * np.abs(phi).max() * 3


def test_gradient_is_the_energy_s():
    nb = two_planets()
    fc = FlowComposed.from_nbody(nb, 0.3)
    Y = fc.extend(nb.initial_state())
    _assert_gradient_of_energy(fc, Y)
    # H~ starts at the physical energy, and the state converts back
    assert fc.energy(Y) == pytest.approx(fc.physical_energy(Y), rel=1e-14)
    assert np.abs(fc.physical(Y) - nb.initial_state()).max() < 1e-14


@pytest.mark.parametrize("s, k, ns", [(2, 4, (32, 64, 128)), (3, 5, (16, 32, 64))])
def test_order_2s(s, k, ns):
    nb = two_planets()
    T = 8.0
    ref = plain_reference(nb, T)
    errs = []
    for n in ns:
        fc, r = composed(nb, s, k, T / n, n, error_bound=None)
        errs.append(np.abs(fc.physical(r.y[-1], T)[:9] - ref[:9]).max())
    slopes = -np.diff(np.log(errs)) / np.log(2)
    assert np.all(np.abs(slopes - 2 * s) < 0.3), (errs, slopes)


def test_agrees_with_plain_hbvm():
    nb = two_planets(1e-3)
    T = 8.0
    ref = plain_reference(nb, T)
    fc, r = composed(nb, 6, 8, T / 32, 32)
    y = fc.physical(r.y[-1], T)
    assert np.abs(y[:9] - ref[:9]).max() < 1e-12
    assert nb.energy(y) == pytest.approx(nb.energy(nb.initial_state()), rel=1e-13)


def test_recentring_is_the_hook_and_deterministic():
    nb = two_planets()
    h = 0.25
    fc = FlowComposed.from_nbody(nb, h)
    Y0 = fc.extend(nb.initial_state())
    m = fc.dim
    one = integrate(HBVM(6, 4), fc, Y0, h, 12, sample_every=1, form="full")
    # after every committed step the flows are recentred: tau is back at -h/2
    assert np.all(one.y[:, m - 1] == -0.5 * h)
    st = Stepper(HBVM(6, 4), fc, Y0, form="full")
    st.run(h, 5, sample_every=5)
    for _ in range(7):
        st.step(h)
    assert np.array_equal(st.y, one.y[-1])         # bit for bit, however the steps are called


def test_close_encounter_is_refused():
    # two planets on crossing orbits meet head on near (0, 1) at t ~ pi/2, 0.02 apart
    x = np.array([[0, 0, 0], [1, 0, 0], [-1.02, 0, 0]])
    v = np.array([[0, 0, 0], [0, 1.0, 0], [0, 1 / np.sqrt(1.02), 0]])
    nb = NBody([1.0, 1e-3, 1e-3], 1.0, positions=x, velocities=v)
    for h in (0.1, 0.5):
        fc = FlowComposed.from_nbody(nb, h)
        st = Stepper(HBVM(8, 6), fc, fc.extend(nb.initial_state()), form="full")
        with pytest.raises(UnresolvedStepError, match="does not resolve the motion of body"):
            for _ in range(int(4 / h)):
                st.step(h)
        assert 0.9 < st.t < 1.6              # refused at the encounter (t ~ pi/2), not before
    # the same steps far from any encounter pass
    fc, r = composed(two_planets(1e-3), 6, 8, 0.5, 16)
    assert r.y.shape[0] == 2


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="`masses`"):
        FlowComposed([1.0, -1e-3], 1.0, 0.1)     # (0 is a test particle)
    with pytest.raises(ValueError, match="`h`"):
        FlowComposed([1.0, 1e-3], 1.0, 0.0)
    with pytest.raises(ValueError, match="`y`"):
        FlowComposed([1.0, 1e-3], 1.0, 0.1).extend(np.zeros(5))


def test_adaptive_steps_are_refused_by_name():
    nb = two_planets()
    fc = FlowComposed.from_nbody(nb, 0.1)
    with pytest.raises(ValueError, match="adaptive steps are not available for FlowComposed"):
        integrate(HBVM(6, 4), fc, fc.extend(nb.initial_state()), 0.1, form="full",
                  adaptive=True, t_end=1.0, epsilon=1e-9)


def test_clock_rate_scales_the_clock_exactly():
    # c tau and p_tau / c with c a power of 2: the same physical states and energy to the bit
    # at the start, the same run to round-off (only the iteration's stop rule sees c), fewer
    # or as many sweeps
    nb = two_planets(1e-3)
    h, n = 0.25, 24
    fc1 = FlowComposed.from_nbody(nb, h)
    fcc = FlowComposed.from_nbody(nb, h, clock_rate=2.0 ** 10)
    Y1, Yc = fc1.extend(nb.initial_state()), fcc.extend(nb.initial_state())
    m = fc1.dim
    assert Yc[m - 1] == 2.0 ** 10 * Y1[m - 1] and Yc[2 * m - 1] == Y1[2 * m - 1] / 2.0 ** 10
    assert np.array_equal(fcc.physical(Yc), fc1.physical(Y1))
    assert fcc.energy(Yc) == fc1.energy(Y1)
    g1, gc = fc1.gradient(Y1)[0], fcc.gradient(Yc)[0]
    assert np.array_equal(np.delete(gc, [m - 1, 2 * m - 1]), np.delete(g1, [m - 1, 2 * m - 1]))
    assert gc[2 * m - 1] == 2.0 ** 10 and gc[m - 1] == g1[m - 1] / 2.0 ** 10
    runs = [Stepper(HBVM(8, 6), fc, Y, form="full") for fc, Y in ((fc1, Y1), (fcc, Yc))]
    for st in runs:
        st.run(h, n, sample_every=n)
    assert runs[1].y[m - 1] == -0.5 * h * 2.0 ** 10          # recentred in its own units
    y1, yc = fc1.physical(runs[0].y, n * h), fcc.physical(runs[1].y, n * h)
    assert np.abs(yc - y1).max() < 1e-13
    assert runs[1].niter <= runs[0].niter


@pytest.mark.parametrize("bad", [3.0, 0.0, -2.0, float("nan"), True, 2.0 ** 70, "2"])
def test_clock_rate_must_be_a_power_of_two(bad):
    with pytest.raises(ValueError, match="`clock_rate`"):
        FlowComposed([1.0, 1e-3], 1.0, 0.1, clock_rate=bad)


class _WithGRPotential(SeparableSystem):
    """An NBody plus REBOUNDx's gr_potential about body 0, -sum_i 3 (G m_0)^2 m_i /
    (c^2 |x_i - x_0|^2), written with numpy in the plain (barycentric) variables: plain HBVM's
    reference for FlowComposed's gr_c."""

    def __init__(self, nb, c):
        self.nb, self.dim, self.masses = nb, nb.dim, nb.masses
        self.m = nb.body_masses
        self.k = 3 * (nb.G * self.m[0]) ** 2 / c ** 2

    def _rel(self, q):
        X = np.asarray(q, dtype=float).reshape(np.shape(q)[:-1] + (-1, 3))
        d = X[..., 1:, :] - X[..., :1, :]
        return X, d, np.sum(d * d, axis=-1)

    def potential(self, q):
        _, _, r2 = self._rel(q)
        return self.nb.potential(q) - self.k * np.sum(self.m[1:] / r2, axis=-1)

    def kinetic(self, p):
        return self.nb.kinetic(p)          # (a test particle weighs nothing in H)

    def forces(self, q):
        # per unit mass on a test particle (NBody's p = v), with no reaction on the star
        X, d, r2 = self._rel(q)
        f = np.zeros_like(X)
        w = np.where(self.m[1:] > 0, self.m[1:], 1.0)
        fi = -2 * self.k * (w / r2 ** 2)[..., None] * d
        f[..., 0, :] = -(fi * (self.m[1:] > 0)[:, None]).sum(axis=-2)
        f[..., 1:, :] = fi
        return self.nb.forces(q) + f.reshape(np.shape(q))


def test_gr_potential_term_is_plain_hbvms_with_the_potential():
    # a strong term (c = 20, G = 1: 3 mu / (c^2 r) ~ 1e-2) so that it moves the planets by far
    # more than the tolerance
    nb = two_planets(1e-3)
    c = 20.0
    ref_sys = _WithGRPotential(nb, c)
    fc = FlowComposed.from_nbody(nb, 0.25, gr_c=c)
    Y = fc.extend(nb.initial_state())
    # H~ starts at H, which is Newton's (barycentric frame) plus the potential; the gradient is
    # H~'s
    y0 = nb.initial_state()
    fc0 = FlowComposed.from_nbody(nb, 0.25)
    U = ref_sys.potential(y0[:9]) - nb.potential(y0[:9])
    assert fc.energy(Y) == pytest.approx(fc.physical_energy(Y), rel=1e-14)
    newton_energy = fc0.physical_energy(fc0.extend(y0))
    assert fc.physical_energy(Y) - newton_energy == pytest.approx(U, rel=1e-12)
    _assert_gradient_of_energy(fc, Y)
    T = 8.0
    r = integrate(HBVM(8, 6), fc, Y, 0.25, 32, sample_every=32, form="full")
    y = fc.physical(r.y[-1], T)
    ref = integrate(HBVM(8, 6), ref_sys, y0, T / 400, 400, sample_every=400,
                    form="full").y[-1]
    newton = integrate(HBVM(8, 6), nb, nb.initial_state(), T / 400, 400, sample_every=400).y[-1]
    assert np.abs(y[:9] - newton[:9]).max() > 1e-4          # the term matters
    assert np.abs(y[:9] - ref[:9]).max() < 1e-12
    assert ref_sys.energy(y) == pytest.approx(ref_sys.energy(y0), rel=1e-13)
    # test particles: REBOUNDx accelerates them too, and they weigh nothing in H
    tp = NBody([1.0, 1e-3, 1e-3 / 2, 0.0], 1.0,
               positions=np.r_[nb.initial_state()[:9].reshape(3, 3), [[0, 1.3, 0]]],
               velocities=np.r_[nb.initial_state()[9:18].reshape(3, 3) / nb.body_masses[:, None],
                                [[-1 / np.sqrt(1.3), 0, 0]]])
    fct = FlowComposed.from_nbody(tp, 0.25, gr_c=c)
    rt = integrate(HBVM(8, 6), fct, fct.extend(tp.initial_state()), 0.25, 32, sample_every=32,
                   form="full")
    yt = fct.physical(rt.y[-1], T)
    reft = _WithGRPotential(tp, c)
    ref_tp = integrate(HBVM(8, 6), reft, tp.initial_state(), T / 400, 400, sample_every=400,
                       form="full").y[-1]
    assert np.abs(yt[:12] - ref_tp[:12]).max() < 1e-12
    assert np.array_equal(yt[:9], y[:9])                     # it pulls nothing


def test_gr_c_absent_is_the_default_and_bad_gr_c_is_named():
    nb = two_planets(1e-3)
    runs = [integrate(HBVM(8, 6), fc, fc.extend(nb.initial_state()), 0.25, 16, sample_every=16,
                      form="full").y[-1]
            for fc in (FlowComposed.from_nbody(nb, 0.25),
                       FlowComposed.from_nbody(nb, 0.25, gr_c=None))]
    assert np.array_equal(runs[0], runs[1])
    for bad in (0.0, -1.0, float("inf"), True, "3e8"):
        with pytest.raises(ValueError, match="`gr_c`"):
            FlowComposed([1.0, 1e-3], 1.0, 0.1, gr_c=bad)


# REBOUNDx's gravitational_harmonics (J2, J4 about a tilted spin axis) and central_force of the
# star, strong enough (G = 1, R_eq = 0.1 at r ~ 1: J2 R^2 / r^2 ~ 1e-3) that an error in a
# formula would show
HARMONICS = (0.1, -0.02, 0.1, (0.0, -np.sin(1.0), np.cos(1.0)))


@pytest.mark.parametrize("central", [(3e-3, 0.5), (2e-3, -1.0)])
def test_harmonics_and_central_force_are_the_energys_gradient(central):
    """The kernel's gradient is H~'s with both terms (and gr_c: the three compose in H_I), the
    log potential of gamma = -1 included, and each term moves the planets."""
    nb = two_planets(1e-3)
    fc = FlowComposed.from_nbody(nb, 0.25, gr_c=20.0, harmonics=HARMONICS, central=central)
    Y = fc.extend(nb.initial_state())
    assert fc.energy(Y) == pytest.approx(fc.physical_energy(Y), rel=1e-14)
    _assert_gradient_of_energy(fc, Y)
    ends = [integrate(HBVM(8, 6), f, f.extend(nb.initial_state()), 0.25, 16, sample_every=16,
                      form="full").y[-1]
            for f in (fc, FlowComposed.from_nbody(nb, 0.25, gr_c=20.0, harmonics=HARMONICS),
                      FlowComposed.from_nbody(nb, 0.25, gr_c=20.0, central=central))]
    assert np.abs(ends[0] - ends[1]).max() > 1e-5 and np.abs(ends[0] - ends[2]).max() > 1e-5
    assert fc.energy(ends[0]) == pytest.approx(fc.energy(Y), rel=1e-13)


def test_harmonics_absent_is_the_default_and_bad_terms_are_named():
    nb = two_planets(1e-3)
    runs = [integrate(HBVM(8, 6), fc, fc.extend(nb.initial_state()), 0.25, 16, sample_every=16,
                      form="full").y[-1]
            for fc in (FlowComposed.from_nbody(nb, 0.25),
                       FlowComposed.from_nbody(nb, 0.25, harmonics=None, central=None))]
    assert np.array_equal(runs[0], runs[1])
    # Omega's length does not matter (REBOUNDx normalises it); the z axis is the default
    a = FlowComposed([1.0, 1e-3], 1.0, 0.1, harmonics=(0.1, 0.0, 0.1))
    b = FlowComposed([1.0, 1e-3], 1.0, 0.1, harmonics=(0.1, 0.0, 0.1, (0, 0, 7.0)))
    assert np.array_equal(a._params, b._params)
    for bad in ((0.0, 0.0, 0.1), (0.1, 0.0, -0.1), (0.1, 0.0, 0.1, (0, 0, 0)), (0.1, 0.1),
                (0.1, float("nan"), 0.1), "J2"):
        with pytest.raises(ValueError, match="`harmonics`"):
            FlowComposed([1.0, 1e-3], 1.0, 0.1, harmonics=bad)
    for bad in ((0.0, 1.0), (1e-3, float("inf")), (1e-3,), (True, 1.0)):
        with pytest.raises(ValueError, match="`central`"):
            FlowComposed([1.0, 1e-3], 1.0, 0.1, central=bad)
