"""The digest of the compiled core's sources (``integrators/csrc``), in one place for the two
that need it: ``setup.py`` builds it into the extension, :mod:`integrators.ccore` compares it
with the sources beside the installed package.  It imports nothing of the package (setup.py
loads this file by its path, before anything is installed)."""
from __future__ import annotations

import hashlib
from pathlib import Path


def source_digest(root) -> str | None:
    """The first 16 hex digits of the SHA-256 of ``root/integrators/csrc/*.[ch]`` (names and
    contents, in name order), or None when there are none (an installed, not editable, package)."""
    files = sorted(Path(root, "integrators", "csrc").glob("*.[ch]"))
    if not files:
        return None
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]
