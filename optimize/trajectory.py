"""The run's files: trajectory.csv and trajectory.json (one record per iteration, written
after every iteration), checkpoint.npz (what `resume` needs to continue the run exactly),
and the figures (objective and metrics against the iteration; template before and after)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import jax
import numpy as np

from jaxvalve.errors import ParameterError

__all__ = ["write_trajectory", "write_checkpoint", "read_checkpoint", "plot_run", "figure"]


def write_trajectory(out: Path, config: dict, records: list, status: dict):
    """trajectory.json (config, status, records) and trajectory.csv (records)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "trajectory.json").write_text(json.dumps(
        dict(config=config, status=status, records=records), indent=1))
    keys = []
    for r in records:
        keys += [k for k in r if k not in keys]
    with open(out / "trajectory.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(records)


def write_checkpoint(out: Path, state, evaluator):
    """checkpoint.npz: the current point, its closed states, the optimiser state."""
    leaves = jax.tree_util.tree_leaves(state.opt_state)
    data = {f"opt_{i}": np.asarray(v) for i, v in enumerate(leaves)}
    for load in evaluator.loads:
        data[f"x_{load}"] = np.asarray(state.evaluation.states[load][1].x)
    np.savez(out / "checkpoint.npz", rab=state.rab, mesh_at=evaluator.mesh_at,
             iteration=state.iteration, value=state.value, grad=state.grad,
             forward=state.counts["forward"], gradient=state.counts["gradient"],
             seconds=state.seconds, **data)


def read_checkpoint(out: Path) -> dict:
    """The checkpoint and the trajectory of a run directory, or `ParameterError`."""
    try:
        traj = json.loads((out / "trajectory.json").read_text())
        with np.load(out / "checkpoint.npz") as z:
            ck = {k: z[k] for k in z.files}
    except (OSError, ValueError, json.JSONDecodeError) as e:
        raise ParameterError(f"cannot resume from {str(out)!r}: {e}") from None
    return dict(trajectory=traj, checkpoint=ck)


def template_outline(r, a, b, alpha, n=120):
    """Closed outline (n, 2) mm of the template A-B-C-D-E-A."""
    from jaxvalve.geometry.template import free_point, sutured_point
    t = np.linspace(0.0, 1.0, n)
    return np.concatenate([sutured_point(t, r, a, alpha), free_point(t[::-1], r, a, b, alpha)])


def plot_run(out: Path, records: list, alpha: float, targets=()):
    """optimisation.png (`figure`) in ``out``; returns its path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = figure(records, alpha, targets, plt)
    path = out / "optimisation.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def figure(records: list, alpha: float, targets=(), plt=None):
    """The run's figure: the objective, the smooth metrics in mm and those in % (one
    panel per unit, each target a labelled dotted line in its metric's colour) against
    the iteration (integer ticks), and the template outline at the start and at the end
    (mm)."""
    from matplotlib.ticker import MaxNLocator

    from .targets import METRICS
    if plt is None:
        from jaxvalve.io.plots import _pyplot
        plt = _pyplot()
    it = [r["iteration"] for r in records]
    names = [k[2:] for k in records[0] if k.startswith("m:") and k != "m:area"]
    units = [u for u in ("mm", "%") if any(METRICS[n][3] == u for n in names)]
    fig, ax = plt.subplots(1, 2 + len(units), figsize=(5 * (2 + len(units)), 4.2))
    ax[0].semilogy(it, [max(r["objective"], 1e-12) for r in records], "o-")
    ax[0].set_ylabel("objective")
    for a, unit in zip(ax[1:], units):
        for n in (n for n in names if METRICS[n][3] == unit):
            line, = a.plot(it, [r[f"m:{n}"] for r in records], "o-", label=n)
            for t in (t for t in targets if t.metric == n):
                for v, how in ((t.lower, ">="), (t.upper, "<="), (t.value, "=")):
                    if v is not None:
                        a.axhline(v, color=line.get_color(), ls=":", lw=1.2,
                                  label=f"target {n} {how} {v:g} {unit}")
        a.set_ylabel(f"smooth metric ({unit})")
        a.legend(fontsize=8)
    for a in ax[:-1]:
        a.set_xlabel("iteration")
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
    for r, style, lab in ((records[0], "--", "start"), (records[-1], "-", "end")):
        p = template_outline(r["r"], r["a"], r["b"], alpha)
        ax[-1].plot(p[:, 0], p[:, 1], style,
                    label=f"{lab}: r={r['r']:.2f}, a={r['a']:.2f}, b={r['b']:.2f} mm")
    ax[-1].set_aspect("equal")
    ax[-1].set_xlabel("mm")
    ax[-1].legend(fontsize=8)
    ax[-1].set_title("template")
    fig.tight_layout()
    return fig
