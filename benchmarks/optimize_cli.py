"""`jaxvalve optimize` with its defaults, timed as a user runs it (issue 4: under 60 s).

    python benchmarks/optimize_cli.py              # 2 runs: empty compilation cache, then warm
    python benchmarks/optimize_cli.py --runs 3     # 3 runs
    python benchmarks/optimize_cli.py --no-check   # passes --no-check to the command
    python benchmarks/optimize_cli.py --no-reference  # skip the machine-speed reference
    python benchmarks/optimize_cli.py --baseline DIR --runs 4  # against a checkout in DIR

Each run is a fresh process running ``jaxvalve optimize --out DIR`` (`jaxvalve.cli.main`), with
``JAXVALVE_CACHE_DIR`` set to a new, empty directory before the first run and kept for the
later ones (so run 1 compiles everything, later runs load XLA executables from the cache).
The table gives the command's wall time, the run's own clock and its compile time (from
``trajectory.json``), the iterations' clock at the last one, the rest of the run clock
(the final check, plus setting up the mesh and writing files, which the iterations' clock
leaves out), the iterations and the objective, and the check's relative gap.  The last line
compares the first run's wall time with the 60 s target.

The target depends on the machine: VMs of the same kind (2 cores) have differed by 2x in
speed between sessions.  So the script ends with a reference that earlier sessions also
recorded: ``jaxvalve simulate`` (the benchmark valve, StVK, rtol 1e-4) with the cache off,
its solve time (both closures, after compilation) and its compile time, measured after the
optimisation runs (README, "Optimisation", lists these figures for each VM).

With ``--baseline DIR`` (a checkout of another commit, e.g. from ``git worktree add``) the
same runs are made with that code as well, interleaved run by run (``PYTHONPATH=DIR``, its
own compilation cache), so that both see the same machine; the script then prints the
ratios of the two codes' cold and mean warm wall times ("this code / baseline").
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from jaxvalve.xla_setup import platform_summary

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkouts import describe, env_for  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 60.0
CLI = "import sys; from jaxvalve.cli import main; sys.exit(main(sys.argv[1:]))"


def run_cli(argv, env, out: Path, root: Path = ROOT) -> float:
    """Run ``jaxvalve ARGV --out OUT`` in a fresh process with ``env`` from the checkout
    ``root``; its wall time (s).  Exits with the command's output when it fails."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CLI, *argv, "--out", str(out)], cwd=root,
                       env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"jaxvalve {argv[0]} exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
    return wall


def run_once(cache: Path, out: Path, extra, root: Path = ROOT) -> dict:
    env = (dict(os.environ, JAXVALVE_CACHE_DIR=str(cache)) if root == ROOT
           else env_for(root, JAXVALVE_CACHE_DIR=str(cache)))
    wall = run_cli(["optimize", *extra], env, out, root)
    d = json.loads((out / "trajectory.json").read_text())
    st, last = d["status"], d["records"][-1]
    chk = st.get("check") or {}
    gap = (abs(chk["value"] - last["objective"]) / abs(last["objective"])
           if chk.get("value") is not None else float("nan"))
    return dict(wall=wall, clock=st["seconds"], compile=st["compile_s"],
                last_it=last["seconds"], iterations=last["iteration"],
                f=last["objective"], gap=gap)


def reference(tmp: Path) -> dict:
    """Solve and compile seconds of a cold ``jaxvalve simulate`` (machine-speed reference)."""
    wall = run_cli(["simulate"], dict(os.environ, JAXVALVE_CACHE_DIR="off"), tmp / "sim")
    t = json.loads((tmp / "sim" / "metrics.json").read_text())["timings"]
    return dict(wall=wall, solve=t["solve"], compile=t["compile"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--no-check", action="store_true")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the machine-speed reference (a cold jaxvalve simulate)")
    ap.add_argument("--baseline", type=Path, default=None, metavar="DIR",
                    help="a checkout of another commit to run interleaved with this code")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error(f"--runs must be at least 1; got {args.runs}")
    base = args.baseline.resolve() if args.baseline is not None else None
    if base is not None and not (base / "jaxvalve" / "cli").is_dir():
        ap.error(f"--baseline must be a jaxvalve checkout (DIR/jaxvalve/cli); got {base}")
    extra = ["--no-check"] if args.no_check else []
    codes = [("this code", ROOT)] + ([("baseline", base)] if base is not None else [])
    rows = {name: [] for name, _ in codes}
    with tempfile.TemporaryDirectory(prefix="jaxvalve_cli_") as tmp:
        for k in range(args.runs):
            for i, (name, root) in enumerate(codes):
                rows[name].append(run_once(Path(tmp) / f"xla{i}", Path(tmp) / f"run{i}_{k}",
                                           extra, root))
        ref = None if args.no_reference else reference(Path(tmp))
    print(f"jaxvalve optimize (defaults{', --no-check' if extra else ''}); run 1 with an "
          f"empty compilation cache, later runs with it filled")
    print(f"platform: {platform_summary()}")
    for name, root in codes:
        if base is not None:
            print(f"## {name}: {describe(root)}")
        _table(rows[name])
    if base is not None:
        _compare(rows["this code"], rows["baseline"])
    if ref is not None:
        print(f"machine-speed reference, jaxvalve simulate with the cache off: solve "
              f"{ref['solve']:.2f} s, compile {ref['compile']:.1f} s, {ref['wall']:.1f} s wall")


def _compare(new: list, old: list) -> None:
    """Ratios of the cold and the mean warm wall times, this code over the baseline."""
    print(f"cold run: {new[0]['wall']:.1f} s against {old[0]['wall']:.1f} s, "
          f"ratio {new[0]['wall'] / old[0]['wall']:.3f}")
    if len(new) > 1:
        wn = sum(r["wall"] for r in new[1:]) / (len(new) - 1)
        wo = sum(r["wall"] for r in old[1:]) / (len(old) - 1)
        cn = sum(r["compile"] for r in new[1:]) / (len(new) - 1)
        co = sum(r["compile"] for r in old[1:]) / (len(old) - 1)
        print(f"warm runs (mean of {len(new) - 1}): {wn:.1f} s against {wo:.1f} s, ratio "
              f"{wn / wo:.3f}; compile {cn:.1f} s against {co:.1f} s")


def _table(rows: list) -> None:
    print(f"{'run':>3} {'cache':>6} {'wall s':>7} {'clock s':>8} {'compile s':>9} "
          f"{'last it s':>9} {'rest s':>7} {'iters':>5} {'objective':>10} {'check gap':>9}")
    for k, r in enumerate(rows):
        print(f"{k + 1:>3} {'empty' if k == 0 else 'warm':>6} {r['wall']:7.1f} "
              f"{r['clock']:8.1f} {r['compile']:9.1f} {r['last_it']:9.1f} "
              f"{r['clock'] - r['last_it']:7.1f} {r['iterations']:5d} {r['f']:10.7f} "
              f"{r['gap']:9.1e}")
    w = rows[0]["wall"]
    print(f"first run (empty cache): {w:.1f} s wall against the {TARGET_S:.0f} s target: "
          f"{'met' if w < TARGET_S else 'MISSED'} ({TARGET_S / w:.2f}x margin)")


if __name__ == "__main__":
    main()
