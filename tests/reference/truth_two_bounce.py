"""The two-bounce test set of tests/solver/test_solver_two_bounce.py and its brute-force truth.

Per chain (RR, RT, TR, TT) ``TWO_BOUNCE_TUPLES`` (default 300) fixed-seed tuples from
two_bounce_data.py (planted paths through both triangles, random pairs) and the paths
tests/reference/bruteforce.py finds in them, computed once per process.  Also used by
bench/two_bounce_recall.py.
"""
from __future__ import annotations

import os
import time

import numpy as np

from reference import bruteforce as bf
from reference.truth import match_paths  # noqa: F401  (re-exported: the same rule on (u1, v1, u2, v2))
from reference.two_bounce_data import plant_two_bounce, random_two_bounce

SEED = 20261121
TUPLES = int(os.environ.get("TWO_BOUNCE_TUPLES", "300"))
FALSE_TOL = 1e-6
RECALL_MARGIN = 1e-7
GRAZE_MARGIN = 1e-4
TIR_MARGIN = 1e-6
SIGMA_MARGIN = 1e-5
DUP_TOL = 1e-9

_CACHE: dict = {}


def make_dataset(chain, n=TUPLES, seed=SEED):
    """planted (tilted normals) 50 %, planted (sphere-like normals) 25 %, random 25 %."""
    rng = np.random.default_rng([seed, ord(chain[0]), ord(chain[1])])
    n1, n2 = n // 2, n // 4
    n3 = n - n1 - n2
    parts = [("planted_tilt", plant_two_bounce(rng, chain, n1, sphere_frac=0.0)),
             ("planted_sphere", plant_two_bounce(rng, chain, n2, sphere_frac=1.0)),
             ("random", random_two_bounce(rng, chain, n3))]
    out = {k: np.concatenate([p[k] for _, p in parts]) for k in parts[0][1]}
    out["cat"] = np.concatenate([np.full(len(p["x0"]), c, dtype=object) for c, p in parts])
    out["chain"] = chain
    return out


def dataset_with_truth(chain):
    if chain not in _CACHE:
        d = make_dataset(chain)
        t = time.time()
        ti, uv, chk = bf.solve_bruteforce(chain, d["x0"], d["x3"], d["P"], d["N"], d["eta"], return_all=True)
        sig = bf.root_sigma_min(chain, d["x0"][ti], d["x3"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv) if len(ti) else np.zeros(0)
        d.update(bf_t=ti, bf_uv=uv, bf_chk=chk, bf_sigma=sig, t_bf=time.time() - t)
        _CACHE[chain] = d
    return _CACHE[chain]
