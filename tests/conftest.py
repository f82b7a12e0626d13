"""Shared test set-up: make ``import addon``, ``fixtures.*`` and ``reference.*`` work from any
working directory.

Layout: solver/, bake/, ui/, packaging/ hold the tests (no test module imports another);
fixtures/ the scene builders and shared measures; reference/ the independent oracles (brute
force, photon tracer, the truth data sets).  Markers (pytest.ini): slow, bpy, opencl, network.
"""

import os
import sys

TESTS = os.path.dirname(os.path.abspath(__file__))
REPO_ROOT = os.path.dirname(TESTS)
for p in (TESTS, REPO_ROOT):
    if p not in sys.path:
        sys.path.insert(0, p)
