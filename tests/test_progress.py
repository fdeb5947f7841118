"""Live progress (`jaxvalve.progress`): the heartbeat's lines and timing, and the beacons
of a compiled solve."""
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen

from jaxvalve import progress
from jaxvalve.mechanics.materials import StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import FIRE


def test_heartbeat_line_phase_beacon_and_estimate():
    lines = []
    hb = progress.Heartbeat(lines.append, every=2.0, unit="members")
    hb.say("closing at 80 mmHg")
    assert lines == ["closing at 80 mmHg"]
    t = hb._t_phase
    # no beacon since the phase began: the run is compiling or setting up
    assert hb.line(t + 5.0) == ("... 5 s in: closing at 80 mmHg; compiling or setting up "
                                "(no solver step yet)")
    progress.beacon(jnp.asarray(300), jnp.asarray(3.25e-3), "FIRE")
    assert hb.line(t + 7.0) == "... 7 s in: closing at 80 mmHg; FIRE step 300, residual 3.25e-03"
    # a new phase forgets the old beacon
    hb.say("measuring coaptation")
    assert "no solver step yet" in hb.line()
    # done / total, and the time left from the mean time per unit so far
    hb.count(3, 9)
    line = hb.line(hb._t0 + 120.0)
    assert "3/9 members done, about 4.0 min left" in line     # 120 s for 3, 6 to go
    hb.count(9, 9)
    assert hb.line(hb._t0 + 360.0).endswith("9/9 members done")
    progress.member_done()
    progress.member_done()
    assert "2 member solves finished" in hb.line()


def test_heartbeat_speaks_when_the_run_is_silent_and_only_then():
    lines = []
    with progress.Heartbeat(lines.append, every=0.2) as hb:
        hb.say("a silent phase")
        time.sleep(1.05)
        n_silent = len(lines) - 1
        hb.count(0, 1)
        for i in range(10):                 # a chatty phase: 10 lines in 0.5 s
            hb.say(f"line {i}")
            time.sleep(0.05)
    beats = [ln for ln in lines if ln.startswith("... ")]
    assert 3 <= n_silent <= 6, lines        # one every 0.2-0.3 s (the thread polls at 0.1 s)
    assert all("a silent phase" in ln for ln in beats)      # none during the chatty phase
    n = len(lines)
    time.sleep(0.4)
    assert len(lines) == n                  # the thread has stopped


def _disk_problem():
    p, t, rim = meshgen.disk(5.0, 6)
    problem, ref = make_problem(p, t, fixed=rim)
    params = Params(ref=ref, material=StVenantKirchhoff(E=1.0, nu=0.45), thickness=0.3,
                    pressure=mmhg(80))
    return problem, params, jnp.asarray(meshgen.lift(p))


def test_a_compiled_solve_reports_its_steps(monkeypatch):
    """A solve from the host sends a beacon after each stretch of whole BEACON_EVERY
    steps, the last at its final step with the solve's own residual: with the stretches
    held at one unit, one beacon every BEACON_EVERY steps."""
    problem, params, x0 = _disk_problem()
    every = progress.BEACON_EVERY
    monkeypatch.setattr(progress, "MAX_STRETCH", 1)
    before = progress.latest()
    sol = equilibrium.solve(problem, params, x0, FIRE(rtol=1e-12, max_steps=2 * every + 50),
                            throw=False)
    after = progress.latest()
    assert int(sol.stats.steps) == 2 * every + 50
    assert after["solver"] == "FIRE" and after["steps"] == 2 * every + 50
    assert after["serial"] - before["serial"] == 3
    np.testing.assert_allclose(after["residual"], float(sol.stats.residual), rtol=1e-12)


def test_stretches_grow_to_their_time_and_do_not_change_the_solve(monkeypatch):
    """`next_stretch` scales a stretch towards STRETCH_S, at most doubling it, within
    [1, MAX_STRETCH]; and where the stretches end does not change a solve: one unit a
    stretch and stretches grown to the cap give the same state, bit for bit."""
    s = progress.STRETCH_S
    assert progress.next_stretch(1, 10.0) == 1                 # slow (compiling): stay
    assert progress.next_stretch(4, 2 * s) == 2                # twice too long: halve
    assert progress.next_stretch(4, s / 100) == 8              # far too short: double
    assert progress.next_stretch(4, s / 1.5) == 6              # a little short: scale
    assert progress.next_stretch(progress.MAX_STRETCH, 1e-6) == progress.MAX_STRETCH
    assert progress.next_stretch(3, 0.0) == 6
    problem, params, x0 = _disk_problem()
    solver = FIRE(rtol=1e-9, max_steps=5000)
    out = []
    for stretch_s in (1e-9, 1e9):       # one unit a stretch; doubling to the cap
        monkeypatch.setattr(progress, "STRETCH_S", stretch_s)
        out.append(equilibrium.solve(problem, params, x0, solver, throw=False))
    a, b = out
    assert a.converged and b.converged
    assert int(a.stats.steps) == int(b.stats.steps) > 2 * progress.BEACON_EVERY
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))


def test_heartbeat_interval_must_be_positive():
    import pytest

    from jaxvalve.errors import ParameterError
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ParameterError, match="every must be a finite number of seconds"):
            progress.Heartbeat(print, every=bad)


_CACHED_SOLVE = """
import sys
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
import jax.numpy as jnp
from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.materials import StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import FIRE, equilibrium
p, t, rim = meshgen.disk(5.0, 4)
problem, ref = make_problem(p, t, fixed=rim)
params = Params(ref=ref, material=StVenantKirchhoff(E=1.0, nu=0.45), thickness=0.3,
                pressure=mmhg(80))
x0 = jnp.asarray(meshgen.lift(p))
top = equilibrium.solve(problem, params, x0, FIRE(rtol=1e-8), throw=False)
def traced_solve(x):
    return equilibrium.solve(problem, params, x, FIRE(rtol=1e-8), throw=False).x
inner = jax.jit(traced_solve)(x0)
print(int(top.stats.steps), float(jnp.max(jnp.abs(inner - top.x))))
"""


def test_a_top_level_solve_is_kept_by_the_persistent_compilation_cache(tmp_path):
    """JAX writes no program that holds a host callback to its persistent compilation
    cache, so a loop that sends its beacons through one is compiled anew in every process
    (a warm `jaxvalve simulate` compiled its solve again: 16.8 s of compilation against
    5.8 s).  A solve called with concrete values runs its loop from the host in stretches
    of BEACON_EVERY steps and sends the beacons itself: its programs are cached.  A solve
    inside a trace gives the same equilibrium."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", _CACHED_SOLVE, str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    steps, diff = done.stdout.split()
    assert int(steps) > progress.BEACON_EVERY          # more than one stretch ran
    assert float(diff) < 1e-12
    cached = {f.name.split("-")[0] for f in tmp_path.iterdir()}
    assert "jit__stretch" in cached, cached

