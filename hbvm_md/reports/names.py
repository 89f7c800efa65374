"""One spelling of scene and case names: ``outer_solar_system``, ``outer-solar-system`` and
``Outer Solar System`` all name the same scene."""
from __future__ import annotations


def scene_key(name: str) -> str:
    """The canonical (lower-case, hyphenated) form of a scene or case name.

    Raises TypeError when ``name`` is not a string.
    """
    if not isinstance(name, str):
        raise TypeError(f"a scene name must be a string (got {type(name).__name__}: {name!r})")
    return "-".join(name.strip().lower().replace("_", " ").replace("-", " ").split())
