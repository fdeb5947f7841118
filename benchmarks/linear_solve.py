"""The barrier Newton solver's linear solve, (K + diag(K) / tau) d = F, by the candidates
of issue 26, on the projected tangents of the benchmark closure, in one process:

* "splu": scipy's SuperLU with the ordering MMD on A^T + A, factorised anew at every
  Newton step, in its default mode;
* "splu symmetric": the same, told that the matrix is symmetric (one ordering for rows
  and columns, diagonal pivots preferred, pivoting still on): the solver's choice;
* "cholmod": a sparse Cholesky factorisation by CHOLMOD through `cholespy` (not a
  dependency of jaxvalve: measured where it is installed, ``pip install cholespy``);
* "pcg lagged": conjugate gradients preconditioned by the SuperLU factor of the other
  tangent of the table (the 3 mmHg state's for the 80 mmHg tangent and back), to
  relative residual 1e-8: the factorisation kept over many steps.

Tangents: at the 3 and the 80 mmHg equilibria of the benchmark valve (StVK, barrier
contact, Newton), at tau = 1 (the first steps) and 1e3 (near convergence).  Prints per
matrix the time to factorise and solve once (the median of 5), the relative residual,
and the ratio of splu's time to each candidate's ("speed-up": above 1 is faster).

    python benchmarks/linear_solve.py [--h 1.5 0.88] [--out benchmarks/results/linear_solve.txt]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.contact.ipc_pairs import build_pairs  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.solvers.barrier_newton import _Model  # noqa: E402
from jaxvalve.valve.closure import _params  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402

try:
    from cholespy import CholeskySolverD, MatrixType
except ImportError:          # measured only where installed
    CholeskySolverD = None


def _timed(f, n=5):
    """(median seconds of n calls after one warm-up, the last result)."""
    out = f()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def _splu(A, **kw):
    lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", **kw)
    return lu.solve


def _cholmod(A):
    c = CholeskySolverD(A.shape[0], A.indptr.astype(np.int32), A.indices.astype(np.int32),
                        np.ascontiguousarray(A.data), MatrixType.CSC)

    def solve(b):
        out = np.zeros_like(b)
        c.solve(np.ascontiguousarray(b), out)
        return out
    return solve


def _pcg(A, precond):
    M = spla.LinearOperator(A.shape, matvec=precond, dtype=float)
    its = []

    def solve(b):
        its.clear()
        x, _ = spla.cg(A, b, M=M, rtol=1e-8, maxiter=500, callback=lambda _: its.append(1))
        return x
    return solve, its


def tangents(h):
    """{(label, tau): A (CSC)} at the 3 and 80 mmHg equilibria of the benchmark closure."""
    sc = Scene(model="stvk", h=h, rtol=1e-6, contact="barrier", solver="newton")
    valve = build_scene_valve(sc)
    res = simulate(sc, valve=valve, throw=False)
    out = {}
    for label, x, p in (("3 mmHg", res.x_he, sc.he_pressure), ("80 mmHg", res.x, sc.pressure)):
        params = _params(valve, sc, sc.material(), p, None)
        model = _Model(valve.problem, params, valve.barrier_topology)
        x = np.asarray(x, float)
        K = model.tangent(x, build_pairs(valve.barrier_topology, x, float(params.contact.dhat)))
        for tau in (1.0, 1e3):
            out[label, tau] = (K + sp.diags(K.diagonal() / tau)).tocsc()
    return out, res.converged


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, nargs="*", default=[1.5, 0.88], help="mesh sizes, mm")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    lines = [f"linear solve of the barrier Newton step; {platform_summary()}",
             "| h mm | state | tau | unknowns | method | factor + solve ms | CG its | "
             "residual | speed-up vs splu |", "|---" * 9 + "|"]
    print("\n".join(lines), flush=True)
    rng = np.random.default_rng(0)
    for h in args.h:
        mats, ok = tangents(h)
        if not ok:
            lines.append(f"h = {h}: the benchmark closure did not converge; no figures")
            print(lines[-1])
            continue
        lagged = {("3 mmHg", t): _splu(mats["80 mmHg", t]) for t in (1.0, 1e3)}
        lagged.update({("80 mmHg", t): _splu(mats["3 mmHg", t]) for t in (1.0, 1e3)})
        for (label, tau), A in mats.items():
            b = rng.normal(size=A.shape[0])
            methods = [("splu", lambda: _splu(A)(b), None),
                       ("splu symmetric", lambda: _splu(A, options=dict(SymmetricMode=True))(b),
                        None)]
            if CholeskySolverD is not None:
                methods.append(("cholmod", lambda: _cholmod(A)(b), None))
            pcg, its = _pcg(A, lagged[label, tau])
            methods.append(("pcg lagged", lambda: pcg(b), its))
            base = None
            for name, f, it in methods:
                t, x = _timed(f)
                base = t if base is None else base
                r = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
                s = (f"| {h} | {label} | {tau:g} | {A.shape[0]} | {name} | {t * 1e3:.1f} | "
                     f"{len(it) if it is not None else '-'} | {r:.1e} | {base / t:.2f}x |")
                lines.append(s)
                print(s, flush=True)
    if CholeskySolverD is None:
        lines.append("cholmod: not measured (cholespy is not installed)")
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
