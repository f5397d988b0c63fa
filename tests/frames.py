"""Comparing frames in tests (export -> import round trips)."""

from __future__ import annotations

import numpy as np

from scenegen_jax.frame import Frame


def frame_differences(a: Frame, b: Frame, atol: float = 1e-4) -> list[str]:
    """Fields in which two frames differ beyond `atol` (m, rad, m/s); [] when they match.

    Headings compare as angles; the map compares lane by lane (ids, types, marks, flags, links,
    boundary points), then crosswalk and drivable-area points, then lines (marks and points).
    `source` is not compared.
    """
    diffs: list[str] = []
    if a.scene_id != b.scene_id:
        diffs.append(f"scene_id: {a.scene_id!r} != {b.scene_id!r}")
    if a.num_actors != b.num_actors:
        return [*diffs, f"num_actors: {a.num_actors} != {b.num_actors}"]
    if not np.array_equal(np.asarray(a.cls), np.asarray(b.cls)):
        diffs.append("cls")
    if [str(t) for t in a.track_id] != [str(t) for t in b.track_id]:
        diffs.append("track_id")
    if not np.array_equal(a.measured, b.measured):
        diffs.append("size_measured")
    for name in ("position", "size", "velocity", "ego_velocity", "ego_size", "city_from_ego"):
        x, y = np.asarray(getattr(a, name), np.float64), np.asarray(getattr(b, name), np.float64)
        if x.shape != y.shape or not np.allclose(x, y, rtol=0, atol=atol):
            diffs.append(name)
    dh = np.angle(np.exp(1j * (np.asarray(a.heading, np.float64) - np.asarray(b.heading))))
    if np.any(np.abs(dh) > atol):
        diffs.append("heading")

    def close(p: np.ndarray, q: np.ndarray) -> bool:
        return p.shape == q.shape and np.allclose(p, q, rtol=0, atol=atol)

    if len(a.map.lanes) != len(b.map.lanes):
        diffs.append(f"map.lanes: {len(a.map.lanes)} != {len(b.map.lanes)}")
    else:
        for i, (la, lb) in enumerate(zip(a.map.lanes, b.map.lanes, strict=True)):
            fields = ("id", "lane_type", "left_mark", "right_mark", "is_intersection")
            for f in (*fields, "successors", "predecessors"):
                if getattr(la, f) != getattr(lb, f):
                    diffs.append(f"map.lanes[{i}].{f}")
            if not (close(la.left, lb.left) and close(la.right, lb.right)):
                diffs.append(f"map.lanes[{i}] boundaries")
    for name in ("crosswalks", "drivable_areas"):
        pa, pb = getattr(a.map, name), getattr(b.map, name)
        if len(pa) != len(pb) or not all(close(p, q) for p, q in zip(pa, pb, strict=True)):
            diffs.append(f"map.{name}")
    la, lb = a.map.lines, b.map.lines
    if len(la) != len(lb) or not all(
        p.mark == q.mark and close(p.points, q.points) for p, q in zip(la, lb, strict=True)
    ):
        diffs.append("map.lines")
    if a.map.dataset != b.map.dataset:
        diffs.append(f"map.dataset: {a.map.dataset!r} != {b.map.dataset!r}")
    return diffs
