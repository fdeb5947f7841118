"""Runs in another checkout of jaxvalve (a helper of the benchmarks, not one itself): the
benchmarks that compare this code with another commit (``--baseline DIR``) run a small
program in fresh processes with ``PYTHONPATH`` set to each checkout.

* `describe(root)`: the checkout's commit, one line.
* `run_json(root, code, argv, what)`: ``python -c code *argv`` in ``root`` with its
  ``PYTHONPATH`` and the compilation cache off (each process compiles afresh, as the other
  code's does); the JSON object on the last line of its output.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def describe(root: Path) -> str:
    """``root``'s commit, "<hash> <subject>" cut to 100 characters (the path where git
    cannot say)."""
    p = subprocess.run(["git", "-C", str(root), "log", "-1", "--format=%h %s"],
                       capture_output=True, text=True)
    return p.stdout.strip()[:100] if p.returncode == 0 else str(root)


def env_for(root: Path, **extra) -> dict:
    """The environment of a process that imports jaxvalve from ``root``: its PYTHONPATH,
    and ``extra`` variables."""
    return dict(os.environ, PYTHONPATH=str(root), **extra)


def run_json(root: Path, code: str, argv, what: str) -> dict:
    """The JSON object that ``code``, run as ``python -c`` with ``argv`` in checkout
    ``root`` (cache off), prints on its last line.  Exits naming ``what`` if it fails."""
    p = subprocess.run([sys.executable, "-c", code, *map(str, argv)], cwd=root,
                       env=env_for(root, JAXVALVE_CACHE_DIR="off"), capture_output=True,
                       text=True)
    if p.returncode != 0:
        raise SystemExit(f"{what} in {root} failed:\n{p.stdout}\n{p.stderr}")
    return json.loads(p.stdout.strip().splitlines()[-1])
