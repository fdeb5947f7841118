"""The paper's material sweeps (Tables 4 and 5) by the CLI, with their progress, to files.

    python benchmarks/sweeps.py --tables 4 5 --h 1.5 --out benchmarks/results/sweep_default_h1.5

Runs ``jaxvalve sweep --table N --h H --out DIR`` for each table, one after the other,
and writes DIR/tableN.txt: the command and the platform, the sweep's table and its
warnings (every member that did not converge, and for a limit point the inflation
analysis of its material, `jaxvalve.mechanics.inflation`), a count line, and its
progress (stderr, XLA's loader lines and the
heartbeat removed).  The CLI itself writes tableN.csv and
tableN.png beside it.  Extra arguments after ``--`` go to every sweep.
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import time
from pathlib import Path


def _noise(line: str) -> bool:
    """XLA's loader lines and the CLI's 2-second heartbeat ("... 12 s in: ...")."""
    return "cpu_aot" in line or line.startswith("[jaxvalve sweep] ... ")


def _count(csv_path: Path) -> str:
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    conv = sum(r["converged"] == "True" for r in rows)
    lims = [r for r in rows if "limit_point" in (r.get("result_he"), r.get("result_closing"))]
    out = f"# converged {conv} of {len(rows)} members; at a limit point {len(lims)}"
    for r in lims:
        out += f"\n#   member {r['member']} ({r['model']}): {r.get('inflation', '')}"
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tables", nargs="+", type=int, default=[4, 5], choices=[4, 5])
    ap.add_argument("--h", type=float, default=None, help="mesh size, mm (default: the CLI's)")
    ap.add_argument("--out", required=True, help="results folder")
    ap.add_argument("extra", nargs="*", help="more `jaxvalve sweep` arguments (after --)")
    args = ap.parse_args(argv)
    from jaxvalve.xla_setup import platform_summary
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    worst = 0
    for table in args.tables:
        cmd = ["sweep", "--table", str(table)] + (["--h", f"{args.h:g}"] if args.h else []) \
            + ["--out", str(out)] + list(args.extra)
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-c", "import sys; from jaxvalve.cli import "
                              "main; sys.exit(main(sys.argv[1:]))", *cmd],
                             capture_output=True, text=True)
        wall = time.perf_counter() - t0
        err = [ln.replace(str(out), "DIR") for ln in run.stderr.splitlines() if not _noise(ln)]
        warn = [ln for ln in err if ln.startswith("jaxvalve sweep:")]
        prog = [ln for ln in err if not ln.startswith("jaxvalve sweep:")]
        shown = " ".join(c if c != str(out) else "DIR" for c in cmd)
        text = [f"# jaxvalve {shown} (exit code {run.returncode}, {wall / 60:.1f} min wall); "
                f"{platform_summary()}", run.stdout.rstrip(), *warn]
        if (out / f"table{table}.csv").exists():
            text.append(_count(out / f"table{table}.csv"))
        text += ["", "# progress (stderr, XLA loader and heartbeat lines removed)", *prog]
        (out / f"table{table}.txt").write_text("\n".join(text) + "\n")
        print("\n".join(text[:3 + len(warn)]), flush=True)
        print(f"wrote {out / f'table{table}.txt'}")
        worst = max(worst, run.returncode)
    return worst


if __name__ == "__main__":
    sys.exit(main())
