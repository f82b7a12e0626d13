"""*Prepare Caustic Solver* compiles what the next bake uses (addon/bake/warm_up.py
``prepare_for``): in a fresh process, prepare for a sample scene, then bake it, and count the
kernel signatures the bake added (each one a compile with a cold Numba cache): none."""

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CHECK = os.path.join(REPO, "tests", "bake", "_prepare_check.py")


def _check(blend, resolution, env=None, timeout=600):
    proc = subprocess.run([sys.executable, CHECK, os.path.join(REPO, "sample_blends", blend), str(resolution)],
                          cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("blend, chains", [("mirror_plane.blend", ["R"]), ("metal_ring.blend", ["R", "RR"])])
def test_the_bake_after_prepare_compiles_nothing(blend, chains):
    out = _check(blend, 32)
    assert out["chains"] == chains  # prepared exactly the chains the plan bakes (point light; sun)
    assert out["prepared"] > 0 and out["new"] == {}


@pytest.mark.slow
def test_with_a_cold_cache_the_bake_after_prepare_compiles_nothing(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"))
    out = _check("water_pool.blend", 32, env=env, timeout=3000)
    assert out["chains"] == ["T"] and out["new"] == {}
    assert os.listdir(tmp_path / "numba_cache")  # the kernels were compiled into the cold cache
