"""Learning curves of the attributes: location, box, heading and velocity NLL per vehicle
against the training step, one line per workdir (from its metrics.jsonl).

Usage: python experiments/plot_curves.py OUT.png LABEL=WORKDIR [LABEL=WORKDIR ...]
"""

from __future__ import annotations

import json
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

TERMS = ("location", "box", "heading", "velocity")


def read_curves(workdir: str) -> dict[str, list[tuple[int, float]]]:
    """{term: [(step, NLL per vehicle)]} from WORKDIR/metrics.jsonl (rows without the
    per-vehicle fields, written before they existed, are skipped)."""
    out: dict[str, list[tuple[int, float]]] = {t: [] for t in TERMS}
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        for line in f:
            row = json.loads(line)
            for t in TERMS:
                v = row.get(f"{t}_per_vehicle")
                if v is not None:
                    out[t].append((row["step"], v))
    return out


def main() -> None:
    out, runs = sys.argv[1], [a.split("=", 1) for a in sys.argv[2:]]
    fig, axes = plt.subplots(1, len(TERMS), figsize=(4.2 * len(TERMS), 3.6))
    for label, workdir in runs:
        curves = read_curves(workdir)
        for ax, t in zip(axes, TERMS, strict=True):
            if curves[t]:
                steps, values = zip(*curves[t], strict=True)
                ax.plot(steps, values, label=label, lw=1.2)
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
