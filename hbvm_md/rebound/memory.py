"""numpy views of memory known by its address: HBVM's state, its context block and REBOUND's
simulation, as the host's Python side reads and writes them (the compiled glue views the same
memory with ``numba.carray``).  A view does not keep the memory alive: its owner does (REBOUND
frees the state with the simulation)."""
from __future__ import annotations

import ctypes

import numpy as np


def int64s(addr: int, n: int) -> np.ndarray:
    """The n int64 words at address ``addr``, as a numpy view (no copy)."""
    return np.frombuffer((ctypes.c_int64 * n).from_address(addr), np.int64)


def doubles(addr: int, n: int) -> np.ndarray:
    """The n doubles at address ``addr``, as a numpy view (n = 0: an empty array)."""
    return np.frombuffer((ctypes.c_double * n).from_address(addr), np.float64) if n else np.zeros(0)
