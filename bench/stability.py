"""Stability where methods fail: method x case -> fraction of brute-force paths found, time.

    .venv/bin/python bench/stability.py [--no-write]

The cases are the independent test set of tests/solver/test_solver_random.py, built by
tests/reference/truth.py (planted paths with tilted or sphere-like normals, tuples built with
two or more paths, random tuples, near total internal reflection for T), ground truth from the
brute force in tests/reference.
Writes the "stability" section of BENCHMARKS.md.
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE, os.path.join(ROOT, "tests")]

from fixtures.checks import found_fraction  # noqa: E402
from reference import truth  # noqa: E402
from solver import write_section  # noqa: E402

from addon.solver.spoly.api import SpecularPolynomialSolver  # noqa: E402
from addon.solver.baselines.newton_sms import NewtonSolver, SMSSolver  # noqa: E402
from addon.solver.baselines.curve_walk import CurveWalkSolver  # noqa: E402

# Methods that solve one chain only (the curve walk has no starting point for a reflection).
CHAIN_ONLY = {"curve-8": "T", "curve-32": "T", "curve-128": "T"}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    methods = {"spoly": SpecularPolynomialSolver(), "newton": NewtonSolver(), "sms-4": SMSSolver(4, 1),
               "sms-32": SMSSolver(32, 1), "sms-128": SMSSolver(128, 1),
               "curve-8": CurveWalkSolver(8), "curve-32": CurveWalkSolver(32), "curve-128": CurveWalkSolver(128)}
    lines = []
    for chain in ("R", "T"):
        d = truth.dataset_with_truth(chain)
        cats = sorted(set(d["cat"]))
        a = (chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"])
        lines.append(f"**{chain}**: {len(d['x0']):,} tuples, {len(d['bf_t']):,} brute-force paths.")
        lines.append("")
        lines.append("| method | µs/tuple | all | " + " | ".join(c.replace("_", " ") for c in cats) + " | NaN |")
        lines.append("|---|---|---|" + "---|" * len(cats) + "---|")
        for name, m in methods.items():
            if CHAIN_ONLY.get(name, chain) != chain:
                continue
            m.solve(*[x[:16] if hasattr(x, "shape") else x for x in a])
            t0 = time.perf_counter()
            res = m.solve(*a)
            dt = (time.perf_counter() - t0) / len(d["x0"]) * 1e6
            ti, uv = res.tuple_index, res.uv
            row = [found_fraction(d, ti, uv, np.ones(len(d["x0"]), bool))] + [found_fraction(d, ti, uv, d["cat"] == c) for c in cats]
            lines.append(f"| {name} | {dt:.2f} | " + " | ".join(f"{100 * f:.2f} %" for f in row) + f" | {int((~np.isfinite(uv)).sum())} |")
        lines.append("")
    lines.append("Fraction of the brute-force paths each method returns (all returned paths are true paths: "
                 "`tests/solver/test_solver_baselines.py` checks it). Newton/MNEE seeds as Path Cuts does (centroid; for T also "
                 "the straight line's crossing); SMS is the biased variant with k uniform seeds; curve-k is the coplanarity-curve "
                 "walk of Granizo-Hidalgo & Holzschuch 2024 restricted to the tuple's triangle (all conic arcs and a closed "
                 "ellipse, longest marching step 1/k; T only: a reflection has no starting point on the curve). All share one "
                 "Newton.")
    body = "\n".join(lines)
    print(body)
    if not args.no_write:
        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "stability", "Stability where methods fail (`bench/stability.py`)", body)


if __name__ == "__main__":
    main()
