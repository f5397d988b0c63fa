"""Simple realism statistics of scenes against their maps: drivable-area share, class mix."""

from __future__ import annotations

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.scene import CLASS_NAMES, VEHICLE


def drivable_share(canvas: np.ndarray, actors, cfg: Config, radius_m: float = 40.0):
    """(vehicle centres on the drivable area, vehicle centres counted) for one unrotated scene.

    Args:
      canvas: [S, S, len(ALL_MAP_CHANNELS)] map canvas of the scene (cache layout).
      actors: numpy Actors [N] in the ego frame.
      cfg: config of the canvas (resolution).
      radius_m: only vehicles within this distance of the ego count.
    """
    drivable = np.asarray(canvas[..., ALL_MAP_CHANNELS.index("drivable_area")], np.float32)
    s = drivable.shape[0]
    half = s * cfg.m_per_px / 2
    pos = np.asarray(actors.position)
    sel = np.asarray(actors.valid) & (np.asarray(actors.cls) == VEHICLE)
    sel &= np.linalg.norm(pos, axis=1) < radius_m
    col = np.floor((pos[sel, 0] + half) / cfg.m_per_px).astype(int)
    row = np.floor((half - pos[sel, 1]) / cfg.m_per_px).astype(int)
    ok = (row >= 0) & (row < s) & (col >= 0) & (col < s)
    return int((drivable[row[ok], col[ok]] > 0.5).sum()), int(sel.sum())


def class_mix(actors_list) -> dict[str, float]:
    """Fraction of actors per class over a list of numpy Actors."""
    counts = np.zeros(len(CLASS_NAMES))
    for a in actors_list:
        cls = np.asarray(a.cls)[np.asarray(a.valid)]
        counts += np.bincount(cls, minlength=len(CLASS_NAMES))[: len(CLASS_NAMES)]
    total = max(counts.sum(), 1)
    return {name: float(c / total) for name, c in zip(CLASS_NAMES, counts, strict=True)}


def real_data_check(cache, cfg: Config, moving_mps: float = 2.0) -> dict:
    """Sanity figures of a prepared cache of real scenes (no model involved).

    Returns a dict with `drivable_share` (vehicle centres within 40 m of the ego on the
    drivable raster, over all scenes), `median_vehicle_length_m`, and
    `heading_velocity_deg`: per scenario (scene ids "<scenario>/<step>"), the median angle
    between heading and velocity direction of vehicles moving faster than `moving_mps`, with
    the number of such vehicle states.
    """
    on = total = moving_on = moving_total = 0
    lengths, per_scenario = [], {}
    a = cache.actors
    for i in range(len(cache)):
        sel = np.asarray(a.valid[i]) & (np.asarray(a.cls[i]) == VEHICLE)
        sub = jax.tree.map(lambda x, i=i: np.asarray(x[i]), a)
        canvas = np.asarray(cache.maps[i], np.float32)
        o, t = drivable_share(canvas, sub, cfg)
        on, total = on + o, total + t
        moving = sub.valid & (np.linalg.norm(sub.velocity, axis=1) > moving_mps)
        o, t = drivable_share(canvas, sub.replace(valid=moving), cfg)
        moving_on, moving_total = moving_on + o, moving_total + t
        lengths.extend(np.asarray(a.size[i])[sel, 1].tolist())
        vel = np.asarray(a.velocity[i])[sel]
        moving = np.linalg.norm(vel, axis=1) > moving_mps
        diff = np.asarray(a.heading[i])[sel][moving] - np.arctan2(vel[moving, 1], vel[moving, 0])
        scenario = cache.scene_ids[i].rsplit("/", 1)[0]
        per_scenario.setdefault(scenario, []).extend(np.abs(np.angle(np.exp(1j * diff))).tolist())
    return {
        "scenes": len(cache),
        "drivable_share": on / max(total, 1),
        "vehicles_within_40m": total,
        "moving_drivable_share": moving_on / max(moving_total, 1),
        "moving_vehicles_within_40m": moving_total,
        "median_vehicle_length_m": float(np.median(lengths)) if lengths else float("nan"),
        "heading_velocity_deg": {
            k: (float(np.degrees(np.median(v))), len(v)) for k, v in per_scenario.items() if v
        },
    }
