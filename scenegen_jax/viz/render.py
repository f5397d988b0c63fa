"""Scene renders in the paper's style: map grey, ego red, vehicles blue, pedestrians orange,
bicyclists green; boxes with heading ticks and velocity arrows."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from scenegen_jax.config import Config  # noqa: E402
from scenegen_jax.files import written_whole  # noqa: E402
from scenegen_jax.geometry import box_corners  # noqa: E402
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, VEHICLE, Actors  # noqa: E402

COLORS = {"ego": "#d62728", VEHICLE: "#1f77b4", PEDESTRIAN: "#ff7f0e", BICYCLIST: "#2ca02c"}
HIGHLIGHT = "#9400d3"


def map_background(map_raster: np.ndarray, channels: tuple[str, ...]) -> np.ndarray:
    """[H, W, 3] RGB: white, drivable light grey, lanes grey, crosswalks dark grey."""
    h, w = map_raster.shape[:2]
    rgb = np.ones((h, w, 3), np.float32)

    def paint(name: str, grey: float):
        if name in channels:
            m = map_raster[..., channels.index(name)] > 0.5
            rgb[m] = grey

    paint("drivable_area", 0.88)
    paint("lane_vehicle", 0.80)
    paint("lane_bus", 0.77)
    paint("lane_bike", 0.74)
    paint("lane_boundary_uncrossable", 0.70)
    paint("crosswalk", 0.55)
    return rgb


def draw_scene(
    ax,
    map_raster: np.ndarray,
    channels: tuple[str, ...],
    actors: Actors,
    ego: Actors,
    cfg: Config,
    highlight: int | None = None,
    title: str | None = None,
) -> None:
    """Draws one scene on `ax` in metres (ego frame); `map_raster` [H, W, len(channels)] is
    the config's grid (`raster.jax_map.draw_maps` draws it from a vector map)."""
    h = cfg.grid.grid_size
    if tuple(np.shape(map_raster)) != (h, h, len(channels)):
        raise ValueError(f"map_raster: shape {tuple(np.shape(map_raster))}, config {cfg.name!r} "
                         f"needs [{h}, {h}, {len(channels)}] (`raster.jax_map.draw_maps` draws it "
                         "from a vector map)")
    half = cfg.grid.region_m / 2
    ax.imshow(
        map_background(np.asarray(map_raster, np.float32), channels),
        extent=(-half, half, -half, half),
        origin="upper",
        interpolation="nearest",
    )
    actor_list = [(COLORS["ego"], ego, -1)]
    valid = np.asarray(actors.valid, bool)
    for i in np.flatnonzero(valid):
        one = Actors(
            *(
                np.asarray(f)[i]
                for f in (
                    actors.cls,
                    actors.position,
                    actors.size,
                    actors.heading,
                    actors.velocity,
                    actors.valid,
                )
            )
        )
        actor_list.append((COLORS[int(one.cls)], one, int(i)))
    for color, a, i in actor_list:
        edge = HIGHLIGHT if i == highlight else "black"
        lw = 2.0 if i == highlight else 0.5
        pos = np.asarray(a.position, np.float64)
        if i >= 0 and int(a.cls) == PEDESTRIAN:
            side = cfg.grid.pedestrian_size_m
            ax.add_patch(plt.Circle(pos, max(side, 0.8), color=color, ec=edge, lw=lw, zorder=3))
        else:
            corners = box_corners(pos, np.asarray(a.size), float(a.heading))
            ax.add_patch(Polygon(corners, closed=True, fc=color, ec=edge, lw=lw, zorder=3))
            front = pos + 0.5 * float(a.size[1]) * np.array([np.cos(a.heading), np.sin(a.heading)])
            ax.plot([pos[0], front[0]], [pos[1], front[1]], color="white", lw=0.8, zorder=4)
        v = np.asarray(a.velocity, np.float64)
        if np.hypot(*v) > 0.2:
            ax.arrow(
                pos[0],
                pos[1],
                v[0] * 0.5,
                v[1] * 0.5,
                color=color,
                width=0.15,
                head_width=0.8,
                length_includes_head=True,
                zorder=5,
            )
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=8)


def save_figure(fig, path: str, dpi: int) -> None:
    """Saves and closes `fig`, whole or not at all (`files.written_whole`: no truncated image
    from a full disk or an interrupt), in the format of the name's extension (without one,
    PNG with `.png` appended, as matplotlib does)."""
    if not os.path.splitext(path)[1]:
        path += ".png"
    with written_whole(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)


def render_scene(path: str, *args, dpi: int = 120, **kwargs) -> None:
    """Renders `draw_scene(*args, **kwargs)` to an image file (PNG by default)."""
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_scene(ax, *args, **kwargs)
    fig.tight_layout()
    save_figure(fig, path, dpi)
