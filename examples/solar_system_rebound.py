"""HBVM driven by REBOUND on the outer solar system (HLW) and on a solar system built from
astropy's built-in ephemeris, compared with REBOUND's own integrators in the same process.

    python examples/solar_system_rebound.py [--t-end 1e5] [--plot energy.png]

(the test suite runs it with a short ``--t-end``)
"""
import argparse

import rebound

from hbvm_md import HBVMIntegrator, compare_rebound
from hbvm_md.reports.plots import energy_error_plot
from systems import outer_solar_system, solar_system


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=1e5, help="days")
    ap.add_argument("--plot", default=None, help="save the energy and angular-momentum error plot to this file")
    args = ap.parse_args(argv)

    # 1. HBVM as a REBOUND integrator: attach, then use REBOUND as usual
    sim = outer_solar_system().to_rebound()
    hb = HBVMIntegrator(sim, s=6, dt=100.0)          # k chosen on the scene
    E0 = sim.energy()
    sim.integrate(args.t_end)
    print(f"{hb.method}: t = {sim.t}, steps = {sim.steps_done}, "
          f"relative energy error {abs(sim.energy() / E0 - 1):.1e}")
    hb.detach()                                       # back to REBOUND's integrator
    assert isinstance(sim, rebound.Simulation)

    # 2. conservation against REBOUND's integrators
    print("\nOuter solar system (HLW Table I.2.3):")
    c1 = compare_rebound("outer-solar-system", args.t_end, hbvm=((6, None, 100.0), (6, None, 250.0)),
                         verbose=True)
    print("Sun (with the inner planets) + Jupiter..Neptune from astropy's built-in ephemeris, J2000:")
    scene = solar_system("2000-01-01T12:00:00", bodies=("sun", "jupiter", "saturn", "uranus", "neptune"),
                         include_inner_in_sun=True)
    compare_rebound(scene, args.t_end, hbvm=((6, None, 100.0),), verbose=True)

    if args.plot:
        path = energy_error_plot(c1.series, args.plot, "Outer solar system", "t [days]",
                                 angular_momentum=c1.angular_momentum_series)
        print(f"saved {path}")

if __name__ == "__main__":
    main()
