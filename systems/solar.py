"""Planetary scenes: the outer solar system of HLW and the solar system from astropy's
built-in ephemeris.

Both return an :class:`systems.nbody.NBody` with initial positions and velocities; hand it to
the engine (``scene.initial_state()``) or to REBOUND (``scene.to_rebound()``).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .nbody import NBody

#: Gaussian gravitational constant squared: G in AU^3 / (solar mass day^2).
G_AU_DAY_MSUN = 0.01720209895 ** 2

_OUTER = (  # Hairer, Lubich, Wanner, Geometric Numerical Integration, Table I.2.3
    ("sun", 1.00000597682, (0, 0, 0), (0, 0, 0)),
    ("jupiter", 0.000954786104043, (-3.5023653, -3.8169847, -1.5507963),
     (0.00565429, -0.00412490, -0.00190589)),
    ("saturn", 0.000285583733151, (9.0755314, -3.0458353, -1.6483708),
     (0.00168318, 0.00483525, 0.00192462)),
    ("uranus", 0.0000437273164546, (8.3101420, -16.2901086, -7.2521278),
     (0.00354178, 0.00137102, 0.00055029)),
    ("neptune", 0.0000517759138449, (11.4707666, -25.7294829, -10.8169456),
     (0.00288930, 0.00114527, 0.00039677)),
    ("pluto", 1 / 1.3e8, (-15.5387357, -25.2225594, -3.1902382),
     (0.00276725, -0.00170702, -0.00136504)),
)


def outer_solar_system() -> NBody:
    """Sun (with the inner planets) and Jupiter ... Pluto at 1994-09-05 0h UT.

    Hairer, Lubich, Wanner, *Geometric Numerical Integration*, Sec. I.2.4, Table I.2.3: AU,
    days, solar masses, G = 2.95912208286e-4.
    """
    names = [b[0] for b in _OUTER]
    return NBody([b[1] for b in _OUTER], G=2.95912208286e-4, positions=[b[2] for b in _OUTER],
                 velocities=[b[3] for b in _OUTER], names=names)


#: Sun / body mass ratios of the IAU 2009 system of astronomical constants (as used by the JPL
#: DE ephemerides); Earth and Moon separately, "earth-moon-barycenter" as their sum.
MASS_RATIOS = {
    "mercury": 6023597.400017,
    "venus": 408523.719,
    "earth": 332946.048166,
    "moon": 332946.048166 * 81.30056907,
    "mars": 3098703.59,
    "jupiter": 1047.348644,
    "saturn": 3497.9018,
    "uranus": 22902.98,
    "neptune": 19412.26,
}
MASS_RATIOS["earth-moon-barycenter"] = 1.0 / (1.0 / MASS_RATIOS["earth"] + 1.0 / MASS_RATIOS["moon"])

BODIES = ("sun", "mercury", "venus", "earth", "moon", "earth-moon-barycenter", "mars", "jupiter",
          "saturn", "uranus", "neptune")
_INNER = ("mercury", "venus", "earth-moon-barycenter", "mars")


def body_mass(name: str) -> float:
    """Mass of a body in solar masses (see :data:`MASS_RATIOS`)."""
    return 1.0 if name == "sun" else 1.0 / MASS_RATIOS[name]


def _posvel(names, epoch):
    from astropy import units as u
    from astropy.coordinates import get_body_barycentric_posvel, solar_system_ephemeris
    from astropy.utils import iers
    iers.conf.auto_download = False      # the built-in ephemeris needs no network
    x = np.empty((len(names), 3))
    v = np.empty((len(names), 3))
    with solar_system_ephemeris.set("builtin"):
        for i, name in enumerate(names):
            p, w = get_body_barycentric_posvel(name, epoch)
            x[i] = p.xyz.to_value(u.au)
            v[i] = w.xyz.to_value(u.au / u.day)
    return x, v


def solar_system(epoch="2000-01-01T12:00:00", bodies: Sequence[str] = ("sun", "jupiter", "saturn", "uranus", "neptune"),
                 include_inner_in_sun: bool = False, units=("au", "day", "solMass")) -> NBody:
    """The Sun and chosen planets at ``epoch`` from astropy's built-in ephemeris.

    Parameters
    ----------
    epoch : astropy.time.Time or str
        A ``Time`` or anything ``Time`` accepts (a string is read in the TDB scale).
    bodies : sequence of str
        Names from :data:`BODIES` (astropy's built-in ephemeris has no Pluto); only these are
        modelled.
    include_inner_in_sun : bool
        Add the masses of the inner planets (Mercury, Venus, Earth-Moon, Mars) that are not in
        ``bodies`` to the Sun, placed at the barycentre of the Sun and those planets (the usual
        outer-solar-system model).  Needs "sun" in ``bodies``.
    units : (length, time, mass)
        Astropy units (or their names) of the result; default AU, day, solar mass.  G follows:
        k^2 = 0.01720209895^2 AU^3 / (solar mass day^2) converted.

    Returns
    -------
    NBody
        Barycentric (solar-system barycentre) positions and velocities, masses from
        :data:`MASS_RATIOS`, bodies in the order given.
    """
    from astropy import units as u
    from astropy.time import Time
    names = [str(b).lower() for b in bodies]
    unknown = [b for b in names if b not in BODIES]
    if unknown or not names:
        raise ValueError(f"`bodies` must be a non-empty sequence of names from {BODIES} "
                         f"(got unknown {unknown or bodies!r})")
    if len(set(names)) != len(names):
        raise ValueError(f"`bodies` lists a body twice (got {names})")
    if include_inner_in_sun and "sun" not in names:
        raise ValueError("`include_inner_in_sun=True` needs 'sun' in `bodies`")
    try:
        L, T, M = (u.Unit(x) for x in units)
        lf = (1 * u.au).to_value(L)
        tf = (1 * u.day).to_value(T)
        mf = (1 * u.solMass).to_value(M)
    except (TypeError, ValueError, u.UnitsError) as exc:
        raise ValueError(f"`units` must be (length, time, mass) astropy units, e.g. "
                         f"('au', 'day', 'solMass') (got {units!r}: {exc})") from None
    t = epoch if isinstance(epoch, Time) else Time(epoch, scale="tdb")
    extra = [b for b in _INNER if include_inner_in_sun and b not in names
             and not (b == "earth-moon-barycenter" and ("earth" in names or "moon" in names))]
    x, v = _posvel(names + extra, t)
    m = np.array([body_mass(b) for b in names + extra])
    if extra:
        i = names.index("sun")
        grp = [i] + list(range(len(names), len(names) + len(extra)))
        mt = m[grp].sum()
        x[i] = (m[grp, None] * x[grp]).sum(0) / mt
        v[i] = (m[grp, None] * v[grp]).sum(0) / mt
        m[i] = mt
    n = len(names)
    G = G_AU_DAY_MSUN * lf ** 3 / (mf * tf ** 2)
    return NBody(m[:n] * mf, G=G, positions=x[:n] * lf, velocities=v[:n] * lf / tf, names=names)
