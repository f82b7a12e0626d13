"""Shared test set-up: make ``import addon``, ``fixtures.*`` and ``reference.*`` work from any
working directory, and the benchmarks' workload generators and tools (bench/: ``workloads``,
``cycles_bake``) importable after everything else.

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
BENCH = os.path.join(REPO_ROOT, "bench")
if BENCH not in sys.path:
    sys.path.append(BENCH)  # last: its modules (solver, bake, plan, ...) never hide another
