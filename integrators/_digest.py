"""The digest of the compiled core's sources (``integrators/csrc``), in one place for the two
that need it: ``setup.py`` builds it into the extension, :mod:`integrators.ccore` compares it
with the sources beside the installed package.  It imports nothing of the package (setup.py
loads this file by its path, before anything is installed)."""
from __future__ import annotations

import hashlib
from pathlib import Path


def _digest(files) -> str:
    """The first 16 hex digits of the SHA-256 of the files' names and contents, in their order."""
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def source_digest(root) -> str | None:
    """The digest of ``root/integrators/csrc/*.[ch]`` (in name order), or None when there are
    none (a package installed without its C sources)."""
    files = sorted(Path(root, "integrators", "csrc").glob("*.[ch]"))
    return _digest(files) if files else None


#: the glue's sources besides its own folder (hbvm_md/rebound/csrc): the layout it is built with
#: (written into hbvm_layout.h by setup.py) and the core's header
GLUE_INPUTS = ("hbvm_md/rebound/layout.py", "integrators/csrc/hbvm_core.h")


def glue_digest(root) -> str | None:
    """The same digest of REBOUND's compiled glue's sources: ``root/hbvm_md/rebound/csrc/*.[ch]``
    (in name order) and :data:`GLUE_INPUTS`; None when they are not there."""
    files = sorted(Path(root, "hbvm_md", "rebound", "csrc").glob("*.[ch]"))
    files += [Path(root, f) for f in GLUE_INPUTS]
    if not all(f.exists() for f in files) or len(files) == len(GLUE_INPUTS):
        return None
    return _digest(files)
