"""Per-step location heatmaps of a sampled scene, like the paper's Figure 7: at each recorded
step, the location distribution of the step's class over the grid (ordering-masked and
renormalised, as the sampler used it) over the map and the actors placed before it."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import PowerNorm  # noqa: E402

from scenegen_jax.config import Config  # noqa: E402
from scenegen_jax.scene import CLASS_NAMES, Actors  # noqa: E402
from scenegen_jax.viz.render import draw_scene, save_figure  # noqa: E402


def render_heatmaps(
    path: str,
    map_raster: np.ndarray,
    channels: tuple[str, ...],
    heatmaps: np.ndarray,
    heatmap_cls: np.ndarray,
    steps: tuple[int, ...],
    actors: Actors,
    ego: Actors,
    cfg: Config,
    title: str | None = None,
    dpi: int = 100,
) -> int:
    """Renders one panel per reached step to a PNG; returns the number of panels.

    Args:
      path: PNG path.
      map_raster: [H, W, C] map channels.
      channels: names of the map channels.
      heatmaps: [Sh, H*W] location probabilities per recorded step (row-major bins).
      heatmap_cls: [Sh] class of each step (-1 not reached, 3 the scene stopped there).
      steps: the step index of each row.
      actors: Actors [N] of the final scene (slot t was placed at step t).
      ego: the ego.
      cfg: config (grid).
      title: optional figure title.
    """
    rows = [i for i, c in enumerate(np.asarray(heatmap_cls)) if c >= 0]
    if not rows:
        rows = [0]
    h = cfg.grid.grid_size
    half = cfg.grid.region_m / 2
    fig, axes = plt.subplots(1, len(rows), figsize=(3.2 * len(rows), 3.4), squeeze=False)
    valid = np.asarray(actors.valid, bool)
    for ax, i in zip(axes[0], rows, strict=True):
        step = int(steps[i])
        before = Actors(
            *(
                np.asarray(f)
                for f in (actors.cls, actors.position, actors.size, actors.heading, actors.velocity)
            ),
            valid=valid & (np.arange(valid.shape[0]) < step),
        )
        c = int(np.asarray(heatmap_cls)[i])
        name = CLASS_NAMES[c] if 0 <= c < len(CLASS_NAMES) else ("stop" if c >= 0 else "-")
        highlight = step if step < valid.shape[0] and valid[step] else None
        draw_scene(
            ax,
            map_raster,
            channels,
            _with_slot(before, actors, highlight),
            ego,
            cfg,
            highlight=highlight,
            title=f"step {step}: {name}",
        )
        probs = np.asarray(heatmaps[i], np.float32).reshape(h, h)
        shown = np.ma.masked_less_equal(probs, 0.0)
        # A square-root colour scale keeps the spread-out mass visible next to the peaks.
        norm = PowerNorm(0.5, vmin=0.0, vmax=max(float(probs.max()), 1e-12))
        ax.imshow(
            shown,
            extent=(-half, half, -half, half),
            origin="upper",
            cmap="magma_r",
            alpha=0.6,
            interpolation="nearest",
            zorder=2,
            norm=norm,
        )
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi)
    return len(rows)


def _with_slot(before: Actors, actors: Actors, slot: int | None) -> Actors:
    """`before` plus the actor of `slot` (the one placed at this step), drawn highlighted."""
    if slot is None:
        return before
    valid = np.asarray(before.valid).copy()
    valid[slot] = bool(np.asarray(actors.valid)[slot])
    return before.replace(valid=valid)
