"""What the panels show about a bake in progress, and whether numba can be imported.
Plain module state (no bpy): the modal bake operator writes it, panels read it."""

import importlib.util


class BakeState:
    """The bake in progress (one at a time)."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.running = False
        self.fraction = 0.0
        self.message = ""

    def start(self):
        self.running = True
        self.fraction = 0.0
        self.message = "starting"

    def update(self, fraction, message):
        if fraction is not None:
            self.fraction = max(0.0, min(1.0, float(fraction)))
        if message:
            self.message = message


STATE = BakeState()

MISSING_NUMBA = (
    "Caustic Bake needs numba and llvmlite, which are bundled with the extension, "
    "but they could not be imported ({}). Reinstall the extension package built for "
    "this platform and Blender version"
)
SHORT_MISSING_NUMBA = "numba/llvmlite missing: reinstall the extension built for this platform"

_numba_missing = None  # cached: None = not checked yet, "" = found, else the missing module's name


def numba_missing():
    """The name of the first of numba / llvmlite that cannot be found ("" if both can), without
    importing them (importlib.util.find_spec; cached, see :func:`forget_numba_check`)."""
    global _numba_missing
    if _numba_missing is None:
        _numba_missing = ""
        for name in ("llvmlite", "numba"):
            try:
                found = importlib.util.find_spec(name) is not None
            except (ImportError, ValueError):
                found = False
            if not found:
                _numba_missing = name
                break
    return _numba_missing


def forget_numba_check():
    """Check again next time (registration, tests)."""
    global _numba_missing
    _numba_missing = None
