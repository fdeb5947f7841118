"""Re-execute the notebooks in place, so that the committed files carry their outputs
(figures and numbers visible without running them).

    pip install -e '.[notebooks]'
    python notebooks/execute.py [NAME.ipynb ...]      # default: every notebook here

Each notebook runs top to bottom in a fresh kernel of this Python (nbclient), with its
default settings (the benchmark mesh, every model), and is written back with its outputs.
A cell that raises stops the run and leaves the file as it was.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def execute(path: Path, timeout: int = 1800) -> float:
    """Run the notebook at ``path`` and write it back with its outputs; returns seconds."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    t = time.perf_counter()
    NotebookClient(nb, timeout=timeout, kernel_name="python3",
                   resources={"metadata": {"path": str(HERE.parent)}}).execute()
    nbformat.write(nb, path)
    return time.perf_counter() - t


def main(argv=None) -> int:
    names = (sys.argv[1:] if argv is None else argv) or sorted(p.name for p in HERE.glob("*.ipynb"))
    unknown = [n for n in names if not (HERE / n).is_file() or not n.endswith(".ipynb")]
    if unknown:
        known = ", ".join(sorted(p.name for p in HERE.glob("*.ipynb")))
        print(f"execute.py: no notebook {', '.join(unknown)} in notebooks/; the notebooks "
              f"are: {known}", file=sys.stderr)
        return 2
    for name in names:
        path = HERE / name
        print(f"executing {path.name} ...", flush=True)
        print(f"  done in {execute(path):.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
