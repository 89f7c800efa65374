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


def _posvel(names, epoch, ephemeris: str = "builtin"):
    from astropy import units as u
    from astropy.coordinates import get_body_barycentric_posvel, solar_system_ephemeris
    from astropy.utils import iers
    iers.conf.auto_download = False      # neither ephemeris needs the network
    x = np.empty((len(names), 3))
    v = np.empty((len(names), 3))
    with solar_system_ephemeris.set(ephemeris):
        for i, name in enumerate(names):
            p, w = get_body_barycentric_posvel(name, epoch)
            x[i] = p.xyz.to_value(u.au)
            v[i] = w.xyz.to_value(u.au / u.day)
    return x, v


def solar_system(epoch="2000-01-01T12:00:00", bodies: Sequence[str] = ("sun", "jupiter", "saturn", "uranus", "neptune"),
                 include_inner_in_sun: bool = False, units=("au", "day", "solMass"),
                 ephemeris: str = "builtin") -> NBody:
    """The Sun and chosen planets at ``epoch`` from astropy's built-in ephemeris or a JPL kernel.

    Parameters
    ----------
    epoch : astropy.time.Time or str
        One time: a scalar ``Time`` or a date string such as "2024-01-01" (read in the TDB
        scale).  Arrays of times, bare numbers (ambiguous: JD or MJD? which scale?) and None
        are refused; for a Julian date pass ``Time(2451545.0, format="jd", scale="tdb")``.
    bodies : sequence of str
        Names from :data:`BODIES` (astropy's ephemerides have no Pluto), "sun" among them (the
        planets would fly off without it); only these are modelled.  A single string is
        refused (it would be read letter by letter).
    ephemeris : str
        "builtin" (default): astropy's built-in ephemeris (ERFA's epv00, a VSOP87 fit), no
        download, good to about 1e-3 AU for the outer planets: integrating one year from
        2024-01-01 misses the ephemeris by 1.2e-3 .. 4.5e-3 AU, with HBVM and with IAS15 alike,
        so the scene is a realistic model, not the true sky.  Or the path of a JPL kernel
        (a ``.bsp`` file such as de440s.bsp, already on disk; needs the ``jplephem`` package),
        used through astropy's ``solar_system_ephemeris``.
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
        :data:`MASS_RATIOS`, bodies in the order given.  ``body_masses`` has one mass per body
        (N,); ``masses`` has one per degree of freedom (3N,), as the integrators need.
    """
    from astropy import units as u
    if isinstance(bodies, str):
        raise ValueError(f"`bodies` must be a sequence of names, e.g. bodies=('sun', {bodies!r}) "
                         f"(got the string {bodies!r}, which would be read letter by letter)")
    names = [str(b).lower() for b in bodies]
    unknown = [b for b in names if b not in BODIES]
    if unknown or not names:
        raise ValueError(f"`bodies` must be a non-empty sequence of names from {BODIES} "
                         f"(got unknown {unknown or bodies!r})")
    if len(set(names)) != len(names):
        raise ValueError(f"`bodies` lists a body twice (got {names})")
    if "sun" not in names:
        raise ValueError(f"`bodies` must include 'sun' (got {names}): without it the planets "
                         f"fly off on straight lines; e.g. bodies=('sun', {', '.join(map(repr, names))})")
    try:
        L, T, M = (u.Unit(x) for x in units)
        lf = (1 * u.au).to_value(L)
        tf = (1 * u.day).to_value(T)
        mf = (1 * u.solMass).to_value(M)
    except (TypeError, ValueError, u.UnitsError) as exc:
        raise ValueError(f"`units` must be (length, time, mass) astropy units, e.g. "
                         f"('au', 'day', 'solMass') (got {units!r}: {exc})") from None
    t = _epoch(epoch)
    ephemeris = _ephemeris(ephemeris)
    extra = [b for b in _INNER if include_inner_in_sun and b not in names
             and not (b == "earth-moon-barycenter" and ("earth" in names or "moon" in names))]
    x, v = _posvel(names + extra, t, ephemeris)
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


def _epoch(epoch):
    """One astropy Time from ``epoch`` (a scalar Time or a date string), or a ValueError."""
    from astropy.time import Time
    if isinstance(epoch, Time):
        if not epoch.isscalar:
            raise ValueError(f"`epoch` must be one time (got a Time array of shape {epoch.shape}); "
                             f"build one scene per epoch, e.g. solar_system(epoch[0])")
        return epoch
    if not isinstance(epoch, str):
        raise ValueError(f"`epoch` must be an astropy Time or a date string such as "
                         f"'2024-01-01T00:00:00' (got {epoch!r}); for a Julian date pass "
                         f"Time({epoch!r}, format='jd', scale='tdb')")
    try:
        return Time(epoch, scale="tdb")
    except ValueError:
        raise ValueError(f"`epoch` must be a date astropy reads, such as '2024-01-01T00:00:00' "
                         f"(ISO, TDB scale) (got {epoch!r})") from None


def _ephemeris(ephemeris) -> str:
    """"builtin" or the path of an existing .bsp file (no downloads)."""
    import os
    if isinstance(ephemeris, os.PathLike):
        ephemeris = os.fspath(ephemeris)
    if not isinstance(ephemeris, str):
        raise ValueError(f"`ephemeris` must be 'builtin' or the path of a JPL .bsp file "
                         f"(got {ephemeris!r})")
    if ephemeris.lower() == "builtin":
        return "builtin"
    if not ephemeris.lower().endswith(".bsp") or not os.path.isfile(ephemeris):
        raise ValueError(f"`ephemeris` must be 'builtin' or the path of a JPL kernel file on disk "
                         f"(got {ephemeris!r}, " + ("not a .bsp file" if not ephemeris.lower().endswith(".bsp")
                                                    else "no such file") +
                         "); download one such as de440s.bsp from JPL (naif.jpl.nasa.gov, "
                         "generic_kernels/spk/planets) first: this function never downloads")
    return ephemeris
