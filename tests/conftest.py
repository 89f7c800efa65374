"""Fixtures shared by test modules."""
import pytest


@pytest.fixture
def runs(monkeypatch):
    """The k of each method ``integrators.integrate`` runs, in order (for code that looks
    ``integrate`` up at call time, as :func:`integrators.kchoice.choose_k` does)."""
    import integrators
    calls = []
    real = integrators.integrate

    def counting(method, *args, **kw):
        calls.append(method.k)
        return real(method, *args, **kw)
    monkeypatch.setattr(integrators, "integrate", counting)
    return calls
