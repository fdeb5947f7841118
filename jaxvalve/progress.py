"""Live progress of long runs: solver beacons and a console heartbeat.

Two halves, apart so that the compiled programs never depend on whether anyone listens:

* **Beacons.**  A single solve called with concrete values runs its compiled loop from the
  host in stretches of whole multiples of `BEACON_EVERY` steps, each lasting about
  `STRETCH_S` (`next_stretch`, `solvers.equilibrium._run_host`), and calls `beacon`
  after each, with the step count and the relative residual: none of its programs holds
  a host callback, which JAX's persistent compilation cache would refuse to store.  The
  engine's Newton finish (a host loop) calls it every step.  A solve inside a trace
  (`jit`, the batch's `vmap`) sends none.  A beacon only stores the latest figures (a
  lock and a few assignments): it prints nothing.
* **The heartbeat.**  `Heartbeat(say)` wraps a command-line run: every line the run prints
  through `Heartbeat.say` becomes the current phase, and a daemon thread prints, whenever
  nothing was printed for ``every`` seconds (default 2), one line with the phase, the time
  spent in it, the latest beacon of that phase (solver step and residual) or "compiling"
  before the first one, and, where the run said how far it is (`Heartbeat.count`), the
  members or iterations done and an estimate of the time left.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Callable

import numpy as np

from .errors import ParameterError

__all__ = ["BEACON_EVERY", "STRETCH_S", "MAX_STRETCH", "next_stretch", "EVERY_S", "beacon",
           "member_done", "latest", "Heartbeat"]

#: Seconds of silence after which the heartbeat prints a line (`Heartbeat`'s default).
EVERY_S = 2.0

#: Loop steps between two beacons of a compiled solve inside a trace, and the unit of a
#: host-driven solve's stretches (a FIRE step costs 0.3-3 ms on the valve, so 100 steps
#: are 0.03-0.3 s).
BEACON_EVERY = 100

#: Seconds a host-driven solve's stretch should last (`next_stretch`): several beacons per
#: heartbeat line, and few enough host round trips that they cost nothing measurable.
STRETCH_S = 0.25

#: The longest stretch of a host-driven solve, in units of `BEACON_EVERY` steps.
MAX_STRETCH = 64


def next_stretch(k: int, seconds: float) -> int:
    """The length (in units of `BEACON_EVERY` steps) of a host-driven solve's next stretch,
    after one of ``k`` units that took ``seconds``: scaled towards `STRETCH_S`, at most
    doubled (the first stretch's time includes its compilation), within [1,
    `MAX_STRETCH`].  Each stretch costs a host round trip (the carry's dispatch and a
    sync): at 100 steps a stretch, about 1.5 % of a FIRE closure at h = 1.5 mm."""
    want = int(k * STRETCH_S / seconds) if seconds > 0 else MAX_STRETCH
    return max(1, min(2 * k, MAX_STRETCH, want))

_lock = threading.Lock()
_latest = {"serial": 0, "steps": None, "residual": None, "solver": None, "t": 0.0,
           "members": 0}


def beacon(steps, residual, solver: str = "") -> None:
    """Record a solver's progress (host side; ``steps`` and ``residual`` may be 0-d
    arrays).  Called from inside compiled loops, so it must not raise."""
    try:
        n, r = int(np.asarray(steps)), float(np.asarray(residual))
    except (TypeError, ValueError):
        return
    with _lock:
        _latest.update(serial=_latest["serial"] + 1, steps=n, residual=r, solver=solver,
                       t=time.monotonic())


def member_done() -> None:
    """Record that one member of a batch has finished its own solver loop (host side)."""
    with _lock:
        _latest["members"] += 1


def latest() -> dict:
    """A copy of the latest beacon: serial (count of beacons so far), steps, residual,
    solver, t (time.monotonic() of the beacon), members (count of batch members whose
    own loop has finished, `member_done`)."""
    with _lock:
        return dict(_latest)


def _duration(s: float) -> str:
    s = max(0.0, s)
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


class Heartbeat:
    """Context manager: print a progress line whenever the run has been silent for
    ``every`` seconds (default `EVERY_S`; see the module docstring).  ``say`` prints one
    line (e.g. a command's own printer).  Use `say` for the run's own lines and `count`
    to tell it how many of how many units (sweep members, optimiser iterations) are
    done."""

    def __init__(self, say: Callable[[str], None], every: float | None = None,
                 unit: str = ""):
        self._print = say
        self.every = float(EVERY_S if every is None else every)
        if not (math.isfinite(self.every) and self.every > 0):
            raise ParameterError(f"Heartbeat: every must be a finite number of seconds > 0; "
                                 f"got {every!r}")
        self.unit = unit
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = None
        now = time.monotonic()
        self._phase, self._t_phase, self._t_said = "starting", now, now
        self._serial, self._members = latest()["serial"], latest()["members"]
        self._done, self._total, self._t0 = 0, None, now

    # ---------------------------------------------------------------- the run's side
    def say(self, msg: str) -> None:
        """Print ``msg`` and make it the current phase."""
        with self._lock:
            now = time.monotonic()
            self._phase, self._t_phase, self._t_said = msg.strip(), now, now
            b = latest()
            self._serial, self._members = b["serial"], b["members"]
        self._print(msg)

    def count(self, done: int, total: int) -> None:
        """``done`` of ``total`` units finished (for the estimate of the time left)."""
        with self._lock:
            self._done, self._total = int(done), int(total)

    # ---------------------------------------------------------------- the thread
    def line(self, now: float | None = None) -> str:
        """The heartbeat line for the present state (what the thread prints)."""
        now = time.monotonic() if now is None else now
        b = latest()
        with self._lock:
            phase, t_phase = self._phase, self._t_phase
            fresh = b["serial"] > self._serial
            members = b["members"] - self._members
            done, total, t0 = self._done, self._total, self._t0
        bits = [f"{_duration(now - t_phase)} in: {phase}"]
        if fresh and b["steps"] is not None:
            who = f"{b['solver']} " if b["solver"] else ""
            res = b["residual"]
            bits.append(f"{who}step {b['steps']}"
                        + (f", residual {res:.2e}" if np.isfinite(res) else ""))
        elif not fresh:
            bits.append("compiling or setting up (no solver step yet)")
        if members:
            bits.append(f"{members} member solve{'s' * (members != 1)} finished")
        if total:
            part = f"{done}/{total} {self.unit} done".replace("  ", " ")
            if 0 < done < total:
                left = (now - t0) * (total - done) / done
                part += f", about {_duration(left)} left"
            bits.append(part)
        return "... " + "; ".join(bits)

    def _run(self):
        while not self._stop.wait(0.1):
            now = time.monotonic()
            with self._lock:
                due = now - self._t_said >= self.every
            if due:
                text = self.line(now)
                with self._lock:
                    self._t_said = now
                self._print(text)

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, name="jaxvalve-heartbeat",
                                        daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        return False
