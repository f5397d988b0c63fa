"""Maximum mean discrepancy between real and generated scenes (paper supplementary sec. 2.2).

Each scene is summarised by four normalised histograms (scene statistics):
  class    3 bins, one per class id (VEHICLE, PEDESTRIAN, BICYCLIST), all actors.
  area     box area width * length, m^2, vehicles and bicyclists (pedestrians have no box).
  speed    |velocity|, m/s, all actors.
  heading  heading relative to the ego, rad, vehicles and bicyclists (a pedestrian's heading
           is not modelled). Relative headings are wrapped to [-w/2, 2pi - w/2) with w the
           bin width, so bin 0 is centred on "same direction as the ego" and bin
           HEADING_BINS // 2 on "oncoming"; neither straddles the wrap-around.
Values beyond the last edge go to the last bin (and below the first to the first). A scene
with no actor of the set a statistic is taken over has no histogram: it is discarded for that
statistic ("empty scenes are discarded since these scene statistics are undefined"). The
"vehicle" variant (supplementary Table 1) takes every statistic over vehicles only; its class
histogram is [1, 0, 0] in every scene, so that row is omitted from `mmd_table`.

Kernel: k(p, q) = exp(-TV(p, q)^2 / (2 sigma^2)), TV(p, q) = 0.5 * sum_b |p_b - q_b| in
[0, 1], sigma = 1 (the graph-statistics MMD of the works the paper cites, [24, 12]).

Estimator: the paper's eq. 19 is the biased V-statistic of MMD^2, with every pair of each set
including an element with itself (1 / |P|^2 and 1 / |Q|^2); that is the default here. It is
>= 0 and exactly 0 for identical sets; its largest value is 2 - 2 exp(-1 / (2 sigma^2))
(~0.787 at sigma = 1), reached when every real histogram has TV = 1 to every generated one and
the histograms within each set are identical. `unbiased=True` gives the U-statistic (diagonal
terms excluded, 1 / (m (m - 1))), which can be slightly negative. Values are MMD^2, the
quantity the paper's tables report.

Scenes may be given as `Actors` (numpy or jax, one scene: leading axis N, with its `valid`
mask), `Scene` (the ego heading is then taken from `scene.ego`), `Frame`, or mappings with the
keys cls, position, size, heading, velocity and optionally valid and ego_heading.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from scenegen_jax.scene import BICYCLIST, NUM_CLASSES, VEHICLE

STATISTICS = ("class", "area", "speed", "heading")
SUBSETS = ("all", "vehicle")

# Bin edges (module constants, fixed so that every method is measured on the same bins).
CLASS_EDGES = np.arange(NUM_CLASSES + 1, dtype=np.float64) - 0.5  # one bin per class id
AREA_EDGES = np.linspace(0.0, 40.0, 21)  # m^2, 2 m^2 bins; buses (~30 m^2) fit, > 40 -> last
SPEED_EDGES = np.linspace(0.0, 30.0, 21)  # m/s, 1.5 m/s bins; > 30 m/s -> last bin
HEADING_BINS = 16  # 22.5 degree bins over the circle
HEADING_WIDTH = 2.0 * np.pi / HEADING_BINS
HEADING_EDGES = (np.arange(HEADING_BINS + 1) - 0.5) * HEADING_WIDTH  # rad, [-w/2, 2pi - w/2]
EDGES: dict[str, np.ndarray] = {
    "class": CLASS_EDGES,
    "area": AREA_EDGES,
    "speed": SPEED_EDGES,
    "heading": HEADING_EDGES,
}
_FIELDS = ("cls", "position", "size", "heading", "velocity")


def scene_arrays(scene: Any, region_m: float | None = None) -> dict[str, np.ndarray]:
    """One scene as numpy arrays of its valid actors, plus the ego heading (rad).

    Args:
      scene: `Actors` (leading axis N), `Scene`, `Frame` or a mapping with keys cls, position,
        size, heading, velocity and optionally valid (bool [N]), size_measured (bool [N])
        and ego_heading (rad).
      region_m: if given, keep only actors whose centre lies in the square region of this
        side (m) centred on the ego, as `scene.in_region` (caches and Frames hold actors
        beyond the region).

    Returns:
      dict with cls int [A], position [A, 2] m, size [A, 2] m, heading [A] rad,
      velocity [A, 2] m/s, size_measured bool [A] (valid actors only) and ego_heading
      (float, rad).
    """
    ego_heading = 0.0
    if hasattr(scene, "actors") and hasattr(scene, "ego"):  # Scene
        ego_heading = float(np.asarray(scene.ego.heading))
        scene = scene.actors
    if isinstance(scene, Mapping):
        get = scene.__getitem__
        valid = scene.get("valid")
        measured = scene.get("size_measured")
        ego_heading = float(scene.get("ego_heading", ego_heading))
    else:

        def get(name: str) -> Any:
            return getattr(scene, name)

        valid = getattr(scene, "valid", None)
        measured = getattr(scene, "size_measured", None)
    out = {name: np.asarray(get(name)) for name in _FIELDS}
    if out["cls"].ndim != 1:
        raise ValueError(f"scene.cls: expected one scene with shape [N], got {out['cls'].shape}")
    n = out["cls"].shape[0]
    mask = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    if mask.shape != (n,):
        raise ValueError(f"scene.valid: shape {mask.shape} does not match cls {(n,)}")
    out["size_measured"] = (np.ones(n, bool) if measured is None
                            else np.broadcast_to(np.asarray(measured, bool), (n,)))
    if region_m is not None:
        pos = out["position"].reshape(n, 2)
        mask = mask & np.all((pos >= -region_m / 2) & (pos < region_m / 2), axis=-1)
    out = {name: value[mask] for name, value in out.items()}
    out["cls"] = out["cls"].astype(np.int64)
    out["ego_heading"] = ego_heading
    return out


def _histogram(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Normalised histogram; values outside [edges[0], edges[-1]) clipped into the end bins."""
    n_bins = len(edges) - 1
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
    counts = np.bincount(idx, minlength=n_bins).astype(np.float64)
    return counts / counts.sum()


def scene_statistics(
    scene: Any, subset: str = "all", region_m: float | None = None
) -> dict[str, np.ndarray | None]:
    """The four histograms of one scene (None where the statistic's actor set is empty).

    Args:
      scene: one scene (see `scene_arrays`).
      subset: "all" (every actor) or "vehicle" (vehicles only).
      region_m: see `scene_arrays`.

    Returns:
      dict statistic -> float64 [bins] normalised histogram, or None for an empty set.
    """
    if subset not in SUBSETS:
        raise ValueError(f"subset must be one of {SUBSETS}, got {subset!r}")
    a = scene_arrays(scene, region_m)
    cls = a["cls"]
    members = np.ones(cls.shape, bool) if subset == "all" else cls == VEHICLE
    boxed = members & ((cls == VEHICLE) | (cls == BICYCLIST))
    rel_heading = np.mod(a["heading"] - a["ego_heading"] + 0.5 * HEADING_WIDTH, 2 * np.pi)
    values = {
        "class": (cls, members),
        # a size the source did not measure is a placeholder, not a statistic of the scene
        "area": (a["size"][:, 0] * a["size"][:, 1], boxed & a["size_measured"]),
        "speed": (np.linalg.norm(a["velocity"], axis=-1), members),
        "heading": (rel_heading - 0.5 * HEADING_WIDTH, boxed),
    }
    out: dict[str, np.ndarray | None] = {}
    for stat, (v, m) in values.items():
        out[stat] = _histogram(np.asarray(v, np.float64)[m], EDGES[stat]) if m.any() else None
    return out


def scene_histograms(
    scenes: Iterable[Any], subset: str = "all", region_m: float | None = None
) -> dict[str, np.ndarray]:
    """Histograms of a set of scenes, empty scenes discarded per statistic.

    Args:
      scenes: iterable of scenes (see `scene_arrays`).
      subset: "all" or "vehicle".
      region_m: see `scene_arrays`.

    Returns:
      dict statistic -> float64 [S_stat, bins]; S_stat counts the scenes with at least one
      actor in the statistic's set (rows sum to 1).
    """
    rows: dict[str, list[np.ndarray]] = {s: [] for s in STATISTICS}
    for scene in scenes:
        for stat, h in scene_statistics(scene, subset, region_m).items():
            if h is not None:
                rows[stat].append(h)
    return {s: np.stack(r) if r else np.zeros((0, len(EDGES[s]) - 1)) for s, r in rows.items()}


def tv_kernel(p: np.ndarray, q: np.ndarray, sigma: float = 1.0, chunk: int = 1 << 22):
    """Gram matrix exp(-TV^2 / (2 sigma^2)) between histograms p [m, B] and q [n, B]."""
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    rows = max(1, chunk // max(1, q.shape[0] * q.shape[1]))  # bound the [rows, n, B] buffer
    out = np.empty((p.shape[0], q.shape[0]))
    for start in range(0, p.shape[0], rows):
        tv = 0.5 * np.abs(p[start : start + rows, None, :] - q[None, :, :]).sum(-1)
        out[start : start + rows] = np.exp(-(tv**2) / (2.0 * sigma**2))
    return out


def rbf_kernel(p: np.ndarray, q: np.ndarray, sigma: float = 1.0):
    """Gram matrix exp(-|p - q|^2 / (2 sigma^2)) between vectors p [m, D] and q [n, D]."""
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    d2 = (p**2).sum(1)[:, None] + (q**2).sum(1)[None, :] - 2.0 * p @ q.T
    return np.exp(-np.maximum(d2, 0.0) / (2.0 * sigma**2))


def mmd(
    histograms_a: np.ndarray, histograms_b: np.ndarray, sigma: float = 1.0, unbiased: bool = False,
    kernel=tv_kernel,
) -> float:
    """MMD^2 between two sets of histograms with the Gaussian-TV kernel (eq. 19 by default),
    or of feature vectors with `kernel=rbf_kernel`.

    Args:
      histograms_a: [m, B] normalised histograms (e.g. real scenes).
      histograms_b: [n, B] normalised histograms (e.g. generated scenes).
      sigma: kernel bandwidth.
      unbiased: U-statistic (within-set diagonal excluded) instead of the paper's V-statistic.
      kernel: the Gram matrix function (p, q, sigma).

    Returns:
      MMD^2 estimate; NaN when a set is too small (empty, or one element with `unbiased`).
    """
    a = np.asarray(histograms_a, np.float64)
    b = np.asarray(histograms_b, np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"histograms must be [m, B] and [n, B], got {a.shape} and {b.shape}")
    m, n = a.shape[0], b.shape[0]
    if min(m, n) < (2 if unbiased else 1):
        return float("nan")
    k_aa, k_bb, k_ab = kernel(a, a, sigma), kernel(b, b, sigma), kernel(a, b, sigma)
    if unbiased:
        xx = (k_aa.sum() - np.trace(k_aa)) / (m * (m - 1))
        yy = (k_bb.sum() - np.trace(k_bb)) / (n * (n - 1))
    else:
        xx, yy = k_aa.mean(), k_bb.mean()
    return float(xx + yy - 2.0 * k_ab.mean())


# Bootstrap resamples of each set behind an MMD interval, and the interval's coverage.
BOOTSTRAP_SAMPLES = 200
BOOTSTRAP_LEVEL = 0.95


def _resampled_mean(gram: np.ndarray, rows: np.ndarray) -> float:
    """The V-statistic's within-set mean of a resample `rows` of a set with Gram matrix
    `gram`: its self-pairs, and the pairs of two distinct original elements (a resample's
    repeats of one element would count its self-similarity again and bias the MMD up)."""
    distinct = rows[:, None] != rows[None, :]
    m = len(rows)
    return float((np.trace(gram[np.ix_(rows, rows)]) + gram[np.ix_(rows, rows)][distinct].sum())
                 / (m + distinct.sum()))


def mmd_interval(a: np.ndarray, b: np.ndarray, sigma: float = 1.0, kernel=tv_kernel,
                 seed: int = 0, samples: int = BOOTSTRAP_SAMPLES) -> list[float]:
    """[low, high]: the BOOTSTRAP_LEVEL percentile interval of `mmd` over `samples` resamples
    of each set with replacement, repeats of one element not paired with each other
    (`_resampled_mean`); NaN when a set is empty. The Gram matrices are computed once."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    m, n = len(a), len(b)
    if min(m, n) < 1:
        return [float("nan")] * 2
    k_aa, k_bb, k_ab = kernel(a, a, sigma), kernel(b, b, sigma), kernel(a, b, sigma)
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(samples):
        i, j = rng.integers(0, m, m), rng.integers(0, n, n)
        values.append(_resampled_mean(k_aa, i) + _resampled_mean(k_bb, j)
                      - 2.0 * k_ab[np.ix_(i, j)].mean())
    tail = 50.0 * (1.0 - BOOTSTRAP_LEVEL)
    return [float(np.percentile(values, tail)), float(np.percentile(values, 100.0 - tail))]


def mmd_table(
    real_scenes: Sequence[Any],
    generated_scenes: Sequence[Any],
    sigma: float = 1.0,
    unbiased: bool = False,
    region_m: float | None = None,
    intervals: dict | None = None,
) -> dict[str, float]:
    """Every MMD row of the paper: {class, area, speed, heading} over all actors and vehicles.

    Args:
      real_scenes: scenes from the evaluation data (see `scene_arrays`).
      generated_scenes: scenes generated by the method under evaluation.
      sigma: kernel bandwidth.
      unbiased: see `mmd`.
      region_m: see `scene_arrays`; pass cfg.grid.region_m when scenes hold actors beyond it.
      intervals: if given, filled with each row's bootstrap interval (`mmd_interval`).

    Returns:
      dict "<statistic>/<subset>" -> MMD^2, e.g. "area/vehicle"; "class/vehicle" is omitted
      (degenerate, see the module docstring). NaN where a set has no non-empty scene.
    """
    real_scenes, generated_scenes = list(real_scenes), list(generated_scenes)
    out: dict[str, float] = {}
    for subset in SUBSETS:
        h_real = scene_histograms(real_scenes, subset, region_m)
        h_gen = scene_histograms(generated_scenes, subset, region_m)
        for stat in STATISTICS:
            if subset == "vehicle" and stat == "class":
                continue
            out[f"{stat}/{subset}"] = mmd(h_real[stat], h_gen[stat], sigma, unbiased)
            if intervals is not None:
                intervals[f"{stat}/{subset}"] = mmd_interval(h_real[stat], h_gen[stat], sigma)
    return out
