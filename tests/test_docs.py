"""The README and docs/ say what the code does: their commands are the CI's, their command
lines parse, and their code blocks run.

Every fenced ```python block of README.md and docs/*.md is run, except those fenced
```python fragment (pieces that need the state of the surrounding prose, or that run for
minutes, such as an optimisation: their code is exercised by the tests named beside them).
A block that closes a valve (`Scene(`) is run on a coarse mesh, h = 3 mm, by inserting
``h=3.0`` into its `Scene(...)` calls: the mesh size is the only change.  ```json blocks
are landmark files (docs/patient-roots.md) and are read as such.
"""
import json
import pathlib
import re
import shlex

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
FENCE = re.compile(r"^```([^\n]*)\n(.*?)^```", re.S | re.M)


def blocks(info_word):
    """(page, index, info, code) for every fenced block whose info string starts with
    ``info_word``."""
    out = []
    for page in PAGES:
        for i, m in enumerate(FENCE.finditer(page.read_text(encoding="utf-8"))):
            info = m.group(1).strip()
            if info.split(" ")[0] == info_word:
                out.append((page, i, info, m.group(2)))
    return out


def _id(b):
    return f"{b[0].name}:{b[1]}"


PYTHON = [b for b in blocks("python") if "fragment" not in b[2].split()]


def test_every_page_is_found_and_some_blocks_run():
    names = {p.name for p in PAGES}
    assert {"README.md", "patient-roots.md", "cli-and-api.md"} <= names
    assert {b[0].name for b in PYTHON} >= {"README.md", "patient-roots.md", "cli-and-api.md"}


def _ci_command():
    lines = (ROOT / ".ci" / "run").read_text().splitlines()
    cmd = [ln for ln in lines if ln.startswith("python3 -m venv")]
    assert len(cmd) == 1, f".ci/run must hold one set-up-and-test line; got {cmd}"
    return cmd[0].strip()


def _readme_two_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Two commands", 1)[1].split("\n## ", 1)[0]
    cmds = [m.group(2).strip() for m in FENCE.finditer(section)]
    assert len(cmds) == 2, f"the README's 'Two commands' section must hold two blocks: {cmds}"
    return cmds


def test_readme_test_command_is_the_ci_command():
    setup, tests = _readme_two_commands()
    assert tests == _ci_command()
    # the first command sets up the same environment (without the test extra) and closes
    # the benchmark valve
    assert setup.startswith("python3 -m venv .venv && .venv/bin/pip install -q -e . && ")
    assert setup.endswith(".venv/bin/jaxvalve simulate --out results")


def _command_lines():
    """Every `jaxvalve ...` line of a ```bash block, comments dropped."""
    out = []
    for page, i, _, code in blocks("bash"):
        for ln in code.splitlines():
            ln = ln.split(" #", 1)[0].strip()
            for part in ln.split("&&"):
                part = part.strip()
                m = re.match(r"^(?:\S*/)?jaxvalve\s+(.*)$", part)
                if m:
                    out.append((f"{page.name}:{i}", m.group(1)))
    return out


def test_documented_command_lines_parse():
    """Each documented `jaxvalve` command line is accepted by the CLI's parser as written
    (flag names, choices, types); a renamed or removed flag fails here."""
    from jaxvalve.cli import SUBCOMMANDS, build_parser

    lines = _command_lines()
    assert len(lines) >= 8
    seen = set()
    parser = build_parser()
    for where, args in lines:
        try:
            ns = parser.parse_args(shlex.split(args))
        except SystemExit:
            pytest.fail(f"{where}: `jaxvalve {args}` does not parse")
        seen.add(ns.command)
    assert {"simulate", "optimize"} <= seen <= set(SUBCOMMANDS)


def _coarse(code):
    return re.sub(r"\bScene\(\s*(\)?)", lambda m: "Scene(h=3.0" + (")" if m.group(1) else ", "),
                  code)


def test_coarse_substitution():
    assert _coarse("Scene()") == "Scene(h=3.0)"
    assert _coarse("Scene(model='gent')") == "Scene(h=3.0, model='gent')"
    assert _coarse("default_scene()") == "default_scene()"


@pytest.mark.parametrize("block", PYTHON, ids=_id)
def test_python_block_runs(block, tmp_path, monkeypatch):
    page, i, _, code = block
    monkeypatch.chdir(tmp_path)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    try:
        exec(compile(_coarse(code), f"{page.name}:block{i}", "exec"), {"__name__": "__doc__"})
    finally:
        plt.close("all")


@pytest.mark.parametrize("block", blocks("json"), ids=_id)
def test_json_landmarks_read(block, tmp_path):
    """A documented landmark file reads, and makes a valid root with the defaults the page
    states (axis and origin), over a stand-in wall."""
    from jaxvalve.io import read_landmarks, read_root, write_surface

    page, i, _, code = block
    f = tmp_path / "landmarks.json"
    f.write_text(code)
    lm = read_landmarks(f)
    json.loads(code)
    com = lm["commissures"]
    wall = tmp_path / "wall.vtu"
    write_surface(wall, np.asarray(com), np.array([[0, 1, 2]]))
    root = read_root(wall, f)
    if page.name == "patient-roots.md":
        np.testing.assert_allclose(root.axis, [0.0, 0.0, -1.0], atol=1e-12)
        np.testing.assert_allclose(root.origin, [0.0, 0.0, -12.0], atol=1e-9)


def test_benchmark_results_page_is_generated_from_the_result_files():
    """docs/benchmarks.md is `benchmarks/results_page.py`'s output for the files under
    benchmarks/results/: a changed or new result file without the page regenerated fails
    here."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        "results_page", ROOT / "benchmarks" / "results_page.py")
    page = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(page)
    text = page.render()
    assert (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8") == text, \
        "docs/benchmarks.md is out of date: run python benchmarks/results_page.py"
    for f in (ROOT / "benchmarks" / "results").rglob("*.txt"):
        assert f"## `{f.relative_to(ROOT).as_posix()}`" in text


def test_relative_links_point_to_files_that_exist():
    """Every relative link ``[text](path)`` and image of README.md and docs/*.md names a
    file of the repository (no path outside it)."""
    bad = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.exists() or ROOT not in path.parents and path != ROOT:
                bad.append(f"{page.name}: {target}")
    assert not bad, bad
