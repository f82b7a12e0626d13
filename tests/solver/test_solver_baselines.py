"""Baseline solvers (Newton/MNEE with Path Cuts seeds, biased SMS) against the same
independent brute force as the polynomial solver: what each finds, case by case.

Real properties, each able to fail: no NaN, zero false paths (independent path check),
Newton returns at most one path per seed, SMS finds more as it gets more seeds, and the
polynomial solver finds at least as much as any baseline in every case."""

import numpy as np
import pytest

from reference import truth
from addon.solver.spoly.api import SpecularPolynomialSolver
from addon.solver.baselines.newton_sms import NewtonSolver, SMSSolver
from fixtures.checks import found_fraction
from reference import bruteforce as bf


@pytest.mark.slow  # the 10,000-tuple brute-force truth (reference/truth.py): ~30-60 s per chain here
@pytest.mark.parametrize("chain", ["R", "T"])
def test_baselines_find_only_true_paths_and_fewer_than_the_polynomials(chain):
    d = truth.dataset_with_truth(chain)
    args = (chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"])
    methods = {
        "spoly": SpecularPolynomialSolver(),
        "newton": NewtonSolver(),
        "sms-4": SMSSolver(seeds=4, seed=1),
        "sms-32": SMSSolver(seeds=32, seed=1),
    }
    cats = sorted(set(d["cat"]))
    table = {}
    for name, method in methods.items():
        res = method.solve(*args)
        ti, uv = res.tuple_index, res.uv
        assert np.isfinite(uv).all(), name
        chk = bf.check_path(chain, d["x0"][ti], d["x2"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv, tol=1e-6)
        assert chk.valid.all(), f"{name}: {int((~chk.valid).sum())} false paths"
        if name == "newton":
            per_tuple = np.bincount(ti, minlength=len(d["x0"]))
            assert per_tuple.max() <= (2 if chain == "T" else 1)
        table[name] = {c: found_fraction(d, ti, uv, d["cat"] == c) for c in cats}
        table[name]["all"] = found_fraction(d, ti, uv, np.ones(len(d["x0"]), bool))
    print(f"\n[{chain}] found fraction of brute-force paths: " + ", ".join(cats))
    for name, row in table.items():
        print(f"  {name:7s} all {row['all']:.4f}  " + "  ".join(f"{c} {row[c]:.3f}" for c in cats))
    assert table["spoly"]["all"] >= 0.9999
    assert table["sms-32"]["all"] > table["sms-4"]["all"]
    for name in ("newton", "sms-4", "sms-32"):
        for c in cats + ["all"]:
            if not np.isnan(table[name][c]):
                assert table["spoly"][c] >= table[name][c], (name, c)
    # Tuples built with two paths: one Newton seed can find at most one of them.
    assert table["newton"]["two_path"] <= 0.75
