"""A run's learning curves: ``log.jsonl`` drawn to ``curves.png`` (losses per stage, held-out
fitness BCE, and the simulated success of each cycle's designs)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no backend switched, no window, no global state

from f2f_jax.fileio import atomic_path


def plot_curves(run_dir) -> Path | None:
    """Draw the curves of ``run_dir/log.jsonl`` (the last record per stage/epoch/cycle) to
    ``run_dir/curves.png``; returns its path, or None when there is no log yet."""
    run_dir = Path(run_dir)
    path = run_dir / "log.jsonl"
    if not path.exists():
        return None
    recs = {}
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a kill
        recs[(r.get("stage"), r.get("cycle", 0), r.get("epoch", -1), r.get("label"))] = r
    recs = list(recs.values())
    fig = Figure(figsize=(16, 3.6))
    axes = fig.subplots(1, 4)
    for ax, stage, title in zip(axes[:3], ("ae", "fn", "gn"),
                                ("shape VAE loss", "fitness BCE", "generator loss")):
        pts = [(r.get("cycle", 0), r["epoch"], r["loss"]) for r in recs
               if r["stage"] == stage and "loss" in r]
        pts.sort()
        ax.plot(range(len(pts)), [p[2] for p in pts], ".-", ms=3)
        ax.set_title(title)
        ax.set_xlabel("epoch (pretraining, then cycles)")
        if stage == "fn":
            ho = [(r.get("cycle", 0), r["epoch"], r["heldout_bce"]) for r in recs
                  if r["stage"] == "fn" and "heldout_bce" in r]
            ho.sort()
            if ho:
                ax.plot([i for i, _ in enumerate(ho)], [h[2] for h in ho], "r.-", ms=3,
                        label="held-out (pretraining)")
                ax.legend(fontsize=7)
    # a run taught by the imprints simulates nothing in its cycles
    cyc = sorted((r["cycle"], r) for r in recs if r["stage"] == "cycle" and "success" in r)
    ax = axes[3]
    if cyc:
        xs = [c for c, _ in cyc]
        succ = np.array([r["success"] for _, r in cyc])
        ax.plot(xs, succ[:, 0], "o-", label="grasp")
        ax.plot(xs, succ[:, 1:5].mean(1), "s-", label="stability avg")
        ax.plot(xs, succ[:, 5:].mean(1), "^-", label="robustness avg")
        ax.plot(xs, [r["feasible"] for _, r in cyc], "k--", label="feasible")
        ax.legend(fontsize=7)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("generated designs per cycle (simulated)")
    ax.set_xlabel("cycle")
    fig.tight_layout()
    out = run_dir / "curves.png"
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=90)
    return out
