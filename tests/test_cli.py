"""The CLI entry point solves the membrane it describes."""
import json

import jax.numpy as jnp
import pytest

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen
from jaxvalve.cli import main
from jaxvalve.mechanics.materials import NeoHookean
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import FIRE


def test_membrane_subcommand_reports_the_equilibrium(capsys):
    assert main(["membrane", "--rings", "3", "--model", "neo-hookean", "--solver", "fire",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    p, t, b = meshgen.disk(5.0, 3)
    prob, ref = make_problem(p, t, fixed=b)
    params = Params(ref=ref, material=NeoHookean(1 / 3), thickness=0.3, pressure=mmhg(80))
    x = equilibrium.solve(prob, params, jnp.asarray(meshgen.lift(p)), FIRE()).x
    assert out["converged"] and out["relative_residual"] < 1e-6
    assert out["centre_deflection_mm"] == pytest.approx(float(x[0, 2]), rel=1e-5)


def test_help_and_missing_subcommand(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "membrane" in capsys.readouterr().out
    assert main([]) == 2
    # every subcommand's help renders (argparse %-formats each help string)
    for name in ("membrane", "optimize", "simulate", "sweep"):
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
        assert f"jaxvalve {name}" in capsys.readouterr().out


def test_bad_input_exits_2_with_the_parameter_named_for_every_subcommand(capsys):
    """`main` maps a `JaxvalveError` of any subcommand to exit code 2 and one line on
    stderr (the shared handler in `jaxvalve.cli`), with no traceback."""
    assert main(["membrane", "--rings", "3", "--E", "-1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxvalve membrane: error:") and "E" in err
    assert main(["simulate", "--h", "-1"]) == 2
    assert capsys.readouterr().err.startswith("jaxvalve simulate: error:")


@pytest.mark.parametrize("argv", [
    ["simulate", "--h", "3"],
    ["sweep", "--table", "4", "--h", "3"],
    ["optimize", "--h", "3"],
])
def test_an_output_path_onto_a_file_is_refused_before_any_solve(argv, tmp_path, capsys,
                                                                 monkeypatch):
    """--out naming an existing file exits 2 before the first solve (the solvers are
    replaced by traps), naming --out and the path; the file is left as it was."""
    import jaxvalve.batch
    import jaxvalve.simulation
    import optimize.evaluate

    def trap(*a, **k):
        raise AssertionError("a solve started before --out was checked")
    monkeypatch.setattr(jaxvalve.simulation, "simulate", trap)
    monkeypatch.setattr(jaxvalve.batch, "simulate_batch", trap)
    monkeypatch.setattr(optimize.evaluate.Evaluator, "__init__", trap)
    f = tmp_path / "results"
    f.write_text("keep me")
    assert main([*argv, "--out", str(f)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and str(f) in err and "existing file" in err
    assert f.read_text() == "keep me"


def test_the_console_command_drops_only_the_spurious_cache_loader_lines():
    """`jaxvalve.cli.run` filters file descriptor 2: a C-level write of XLA's spurious
    cache-loader warning is dropped, every other line (Python's and C's) passes, in order,
    and the exit code is main's."""
    import subprocess
    import sys
    code = (
        "import os, sys\n"
        "import jaxvalve.cli as c\n"
        "def fake(argv=None):\n"
        "    os.write(2, b'E1126 cpu_aot_loader.cc:195] Loading XLA:CPU AOT result. Target "
        "machine feature +prefer-no-gather is not supported\\n')\n"
        "    os.write(2, b'a C-level line\\n')\n"
        "    print('a Python line', file=sys.stderr)\n"
        "    return 3\n"
        "c.main = fake\n"
        "c.run()\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 3
    assert done.stderr == "a C-level line\na Python line\n"


def test_a_warm_compilation_cache_prints_no_cache_loader_warning(tmp_path):
    """The console command run twice on one compilation cache (the second run loads the
    cached executables): no line of the second run's stderr comes from XLA's cache
    loader, while jaxvalve's own warnings still reach it."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, JAXVALVE_CACHE_DIR=str(tmp_path / "xla"))
    argv = [sys.executable, "-c", "from jaxvalve.cli import run; run()", "simulate",
            "--h", "3", "--max-steps", "20"]
    runs = [subprocess.run(argv, capture_output=True, text=True, env=env, timeout=600)
            for _ in range(2)]
    assert any((tmp_path / "xla").iterdir())          # the first run filled the cache
    for done in runs:
        assert done.returncode == 3 and "did NOT converge" in done.stderr
        assert "cpu_aot_loader" not in done.stderr
