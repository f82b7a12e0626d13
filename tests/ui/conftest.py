"""Set-up shared by the UI tests (bpy module): the add-on registered once per test module,
and ``fresh_state`` (used by the modules that drive the operators) for a clean operator state
around each test."""

import time

import pytest


@pytest.fixture(scope="module", autouse=True)
def registered():
    pytest.importorskip("bpy")
    import addon

    addon.register()
    yield
    addon.unregister()


@pytest.fixture
def fresh_state():
    """The operator state and the numba check reset before and after the test; afterwards,
    a cancelled bake's last chunk is waited for (at most 120 s) so it cannot touch the next."""
    from addon.ui import operators, state

    state.STATE.reset()
    state.forget_numba_check()
    yield
    deadline = time.monotonic() + 120
    while operators.abandoned_running() and time.monotonic() < deadline:
        time.sleep(0.01)
    state.STATE.reset()
    state.forget_numba_check()
