"""Learning curves of the attributes: location, box, heading and velocity NLL per vehicle
against the training step, one line per workdir (from its metrics.jsonl).

Usage: python experiments/plot_curves.py OUT.png [--max-step N] [--smooth K]
       LABEL=WORKDIR|METRICS.jsonl [...]
(--smooth K: running mean over K logged rows, each one batch and so noisy.)
"""

from __future__ import annotations

import argparse
import json
import math
import os

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

TERMS = ("location", "box", "heading", "velocity")


def read_curves(workdir: str) -> dict[str, list[tuple[int, float]]]:
    """{term: [(step, NLL per vehicle)]} from WORKDIR/metrics.jsonl, or from a metrics file
    itself (a path ending in .jsonl). Rows without the per-vehicle fields, written before
    they existed, are skipped."""
    out: dict[str, list[tuple[int, float]]] = {t: [] for t in TERMS}
    path = workdir if workdir.endswith(".jsonl") else os.path.join(workdir, "metrics.jsonl")
    with open(path) as f:
        for line in f:
            row = json.loads(line)
            for t in TERMS:
                v = row.get(f"{t}_per_vehicle")
                if v is not None:
                    out[t].append((row["step"], v))
    return out


def smooth(values, k: int) -> np.ndarray:
    """Running mean over the last k values (fewer at the start)."""
    c = np.cumsum(np.concatenate([[0.0], values]))
    n = np.arange(1, len(values) + 1)
    return (c[n] - c[np.maximum(n - k, 0)]) / np.minimum(n, k)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("runs", nargs="+", metavar="LABEL=WORKDIR")
    ap.add_argument("--max-step", type=int, default=None)
    ap.add_argument("--smooth", type=int, default=1)
    args = ap.parse_args()
    out, runs = args.out, [a.split("=", 1) for a in args.runs]
    fig, axes = plt.subplots(1, len(TERMS), figsize=(4.2 * len(TERMS), 3.6))
    for label, workdir in runs:
        curves = read_curves(workdir)
        for ax, t in zip(axes, TERMS, strict=True):
            rows = [r for r in curves[t] if args.max_step is None or r[0] <= args.max_step]
            if rows:
                steps, values = zip(*rows, strict=True)
                ax.plot(steps, smooth(values, args.smooth), label=label, lw=1.2)
    for ax, t in zip(axes, TERMS, strict=True):
        ax.set_title(f"{t} NLL per vehicle (train)")
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[2].axhline(math.log(2 * math.pi), color="k", ls=":", lw=1, label="uniform (log 2 pi)")
    axes[0].legend(fontsize=7)
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
