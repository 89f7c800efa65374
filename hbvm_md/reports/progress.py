"""Progress bars for long runs: a tqdm bar on a terminal, silence otherwise (logs, CI, pipes)."""
from __future__ import annotations

import sys


class _Quiet:
    """The part of tqdm's interface the package uses, doing nothing."""

    def __init__(self, iterable=None):
        self.iterable = iterable

    def __iter__(self):
        return iter(self.iterable if self.iterable is not None else ())

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        pass

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        return False


def on_terminal(stream=None) -> bool:
    """True when ``stream`` (default stderr, where bars are drawn) is an interactive terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress(iterable=None, total: int | None = None, desc: str | None = None, enabled: bool | None = None):
    """A tqdm progress bar over ``iterable`` (or a manual one with ``total``) on a terminal.

    Parameters
    ----------
    iterable : iterable, optional
    total : int, optional
    desc : str, optional
    enabled : bool, optional
        Force the bar on or off; default: on only when stderr is a terminal.

    Returns
    -------
    tqdm.tqdm or a silent stand-in with the same ``update``/``close``/iteration interface.
    """
    if not (on_terminal() if enabled is None else enabled):
        return _Quiet(iterable)
    from tqdm import tqdm
    return tqdm(iterable, total=total, desc=desc, leave=False, file=sys.stderr)
