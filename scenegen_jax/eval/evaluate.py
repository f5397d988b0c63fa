"""The paper's Table 1 protocol on one split: NLL of real scenes, and MMD of scenes generated
by SceneGen and the baselines against the real ones, all on the same conditioning scenes; the
real scenes' two halves against each other give the floor ("Real (split)")."""

from __future__ import annotations

import collections
import logging
import sys

import jax
import numpy as np
from tqdm import tqdm

from scenegen_jax.config import Config
from scenegen_jax.data.cache import Cache
from scenegen_jax.data.sources import read_frames
from scenegen_jax.eval import baselines
from scenegen_jax.eval.features import features_interval, features_mmd, scene_features
from scenegen_jax.eval.layout_vae import layout_vae_scores, sample_layout_vae, summarize
from scenegen_jax.eval.mmd import BOOTSTRAP_LEVEL, mmd_table
from scenegen_jax.eval.nll import score_cache, summarize_by_source, summarize_scores
from scenegen_jax.eval.realism import map_canvases, realism_stats
from scenegen_jax.likelihood.batch import grid_scene
from scenegen_jax.likelihood.host_data import cache_maps
from scenegen_jax.sampling.batch import sample_scenes, seed_key
from scenegen_jax.sampling.rollout import DEFAULT_OPTIONS, SamplerOptions

log = logging.getLogger(__name__)
# Table 1's rows in the paper's order; a learned baseline's row is there when its model is
# given (`companions`).
METHODS = ("Prob. Grammar", "MetaSim", "Procedural", "Lane Graph", "LayoutVAE", "SceneGen")
FLOOR = "Real (split)"
MMD_ROWS = ("features", "class/all", "area/all", "speed/all", "heading/all", "area/vehicle",
            "speed/vehicle", "heading/vehicle")  # fmt: skip


def real_scenes(cache: Cache, indices, cfg: Config):
    """(maps [B,H,W,C], Scenes) of cached scenes, unrotated, as numpy."""
    maps, scenes = zip(*(grid_scene(cache, int(i), cfg.grid) for i in indices), strict=True)
    return np.stack(maps), list(scenes)


def sample_scenegen(params, cfg: Config, maps, scenes, seed: int, batch_size: int = 8,
                    options: SamplerOptions = DEFAULT_OPTIONS):
    """One SceneGen sample per conditioning scene (numpy Actors each); scene i is scene i of
    the request (`sampling.scene_key`), whatever the batch size."""
    key = seed_key(seed)
    out = []
    for start in tqdm(range(0, len(scenes), batch_size), desc="sample", unit="batch",
                      file=sys.stderr):
        chunk = scenes[start : start + batch_size]
        egos = jax.tree.map(lambda *x: np.stack(x), *[s.ego for s in chunk])
        sample = sample_scenes(key, params, cfg, maps[start : start + batch_size], egos,
                               first=start, options=options)
        actors = jax.device_get(sample.actors)
        out.extend(jax.tree.map(lambda x, j=j: x[j, 0], actors) for j in range(len(chunk)))
    return out


def sample_baselines(cfg: Config, cache: Cache, indices, train_cache: Cache, seed: int):
    """{method: [numpy Actors]} from Prob. Grammar and Procedural on the scenes' vector maps.

    `cache` (and `train_cache`) may be a `data.union.CacheUnion`: each scene's map is read
    again from its own cache's source."""
    members = getattr(cache, "members", [cache])
    offsets = np.asarray(getattr(cache, "offsets", [0, len(cache)]))
    indices = np.asarray(indices, np.int64)
    frames = [None] * len(indices)
    for m, member in enumerate(members):
        mine = np.flatnonzero((indices >= offsets[m]) & (indices < offsets[m + 1]))
        if not len(mine):
            continue
        wanted = {member.scene_ids[int(indices[n] - offsets[m])]: int(n) for n in mine}
        spec = member.meta.get("source") or {}
        if not spec:
            raise ValueError(f"{member.path}/meta.json: field source missing; re-run prepare")
        for frame in read_frames({**spec, "stride": 1}, collections.Counter()):
            if frame.scene_id in wanted:
                frames[wanted[frame.scene_id]] = frame
        missing = [sid for sid, n in wanted.items() if frames[n] is None]
        if missing:
            raise ValueError(f"{spec.get('root')}: scenes {missing[:3]} not found in the source")
    kde = baselines.fit_size_kde(train_cache.actors, region_m=cfg.grid.region_m)
    rng = np.random.default_rng(seed)
    return {
        "Prob. Grammar": [baselines.prob_grammar(rng, f, cfg) for f in frames],
        "Procedural": [baselines.procedural(rng, f, cfg, kde) for f in frames],
    }


def features_rows(forecaster, maps, scenes, egos, generated: dict) -> dict:
    """{method: (Features MMD^2 against the real scenes, its bootstrap interval)}, and
    FLOOR's: the real scenes' even against their odd halves, each on its own maps; `egos`:
    the scenes' egos stacked (Actors [n])."""
    fcfg, fparams = forecaster
    real = [s.actors for s in scenes]
    f_real = scene_features(fparams, fcfg, maps, real, egos)
    pairs = {m: (f_real, scene_features(fparams, fcfg, maps, generated[m], egos))
             for m in generated}
    pairs[FLOOR] = (f_real[0::2], f_real[1::2])
    return {m: (features_mmd(a, b), features_interval(a, b)) for m, (a, b) in pairs.items()}


def _maps_for(grid, cfg: Config, maps, cache, indices):
    """The conditioning scenes' maps with the channels `grid` reads: the model's own maps when
    they are the same channels, else drawn again."""
    if grid.map_channels == cfg.grid.map_channels:
        return maps
    return cache_maps(cache, grid, indices, progress=False)


def evaluate(params, cfg: Config, cache: Cache, train_cache: Cache, num_scenes: int, seed: int,
             options: SamplerOptions = DEFAULT_OPTIONS, companions: dict | None = None):
    """NLL of every cached scene (overall and per source), and MMD rows and realism figures
    (`realism.realism_stats`) for every method and the real scenes on `num_scenes` scenes
    spread evenly over all of them; SceneGen samples with `options`. `cache` may be a
    `data.union.CacheUnion` of several caches (sources).

    `companions`: {kind: (config, parameters)} of models at `cfg`'s grid shipped beside it
    (`pretrained.load_companion`): with "forecaster" the MMD rows include "features"; with
    "layoutvae" LayoutVAE is a method, with its Monte-Carlo NLL in "baseline_nll"."""
    if num_scenes < 1:
        raise ValueError(f"num_scenes must be >= 1, got {num_scenes}")
    companions = dict(companions or {})
    for kind, (ccfg, _) in companions.items():
        same = ("grid_size", "m_per_px", "zero_speed", "pedestrian_size_m")
        if any(getattr(ccfg.grid, f) != getattr(cfg.grid, f) for f in same):
            raise ValueError(f"the {kind} reads the grid {ccfg.grid}, the model {cfg.grid}: "
                             f"their {', '.join(same)} differ, so it would not read the "
                             "model's scenes")
    seed_key(seed)  # checked now, not after the scoring
    train_cache.check_config(cfg)
    scores = score_cache(params, cache, cfg)
    nll = summarize_scores(scores)
    nll_by_source = summarize_by_source(scores, cache)
    indices = np.linspace(0, len(cache) - 1, min(num_scenes, len(cache))).astype(int)
    maps, scenes = real_scenes(cache, indices, cfg)
    generated = sample_baselines(cfg, cache, indices, train_cache, seed)
    egos = jax.tree.map(lambda *x: np.stack(x), *[s.ego for s in scenes])
    baseline_nll = {}
    if "layoutvae" in companions:
        lcfg, lparams = companions["layoutvae"]
        generated["LayoutVAE"] = sample_layout_vae(
            lparams, lcfg, _maps_for(lcfg.grid, cfg, maps, cache, indices), egos, seed)
        baseline_nll["LayoutVAE"] = summarize(layout_vae_scores(lparams, lcfg, cache, seed))
    generated["SceneGen"] = sample_scenegen(params, cfg, maps, scenes, seed, options=options)
    methods = [m for m in METHODS if m in generated]
    real = [s.actors for s in scenes]
    halves = {**{m: (real, generated[m]) for m in methods}, FLOOR: (real[0::2], real[1::2])}
    interval = {m: {} for m in halves}
    mmd = {m: mmd_table(a, b, region_m=cfg.grid.region_m, intervals=interval[m])
           for m, (a, b) in halves.items()}
    if "forecaster" in companions:
        fmaps = _maps_for(companions["forecaster"][0].grid, cfg, maps, cache, indices)
        for m, (value, low_high) in features_rows(companions["forecaster"], fmaps, scenes, egos,
                                                  generated).items():
            mmd[m]["features"], interval[m]["features"] = value, low_high
    canvases = list(map_canvases(cache, indices, cfg))
    realism = {m: realism_stats(canvases, generated[m], cfg) for m in methods}
    realism["real"] = realism_stats(canvases, real, cfg)
    return {"nll": nll, "nll_by_source": nll_by_source, "baseline_nll": baseline_nll,
            "mmd": mmd, "mmd_interval": interval, "realism": realism,
            "conditioning_scenes": len(indices)}


def format_table(report: dict) -> str:
    """The report as a text table in the layout of the paper's Table 1."""
    nll = report["nll"]
    cols = ["method", "NLL/scene", *MMD_ROWS]
    lines = [" | ".join(cols), " | ".join("---" for _ in cols)]
    for m in (*METHODS, FLOOR):
        if m not in report["mmd"]:
            continue
        scene_nll = (f"{nll['scene_nll']:.1f}" if m == "SceneGen" else
                     f"{report['baseline_nll'][m]['scene_nll']:.1f}"
                     if m in report.get("baseline_nll", {}) else "-")
        row = [_with_interval(report["mmd"][m].get(r),
                              report.get("mmd_interval", {}).get(m, {}).get(r))
               for r in MMD_ROWS]
        lines.append(" | ".join([m, scene_nll, *row]))
    lines.append(f"MMD^2 on {report['conditioning_scenes']} conditioning scenes, in brackets "
                 f"its {BOOTSTRAP_LEVEL:.0%} bootstrap interval; {FLOOR}: the real scenes' "
                 "halves against each other")
    lines.append("")
    lines.append("realism | vehicles on drivable (of within 40 m) | lane-aligned (of on a lane) "
                 "| median offset of the aligned | overlapping pairs | actors/scene "
                 "| vehicle / pedestrian / bicyclist")
    for m, r in report["realism"].items():
        mix = " / ".join(f"{v:.2f}" for v in r["class_mix"].values())
        lines.append(f"{m} | {_share(r['on_drivable_share'])} ({r['vehicles_within_40m']}) | "
                     f"{_share(r['lane_aligned_share'])} ({r['vehicles_on_lane']}) | "
                     f"{_degrees(r.get('lane_offset_median_deg'))} | "
                     f"{r['overlapping_pairs']} | {r['actors_per_scene']:.1f} | {mix}")
    unmeasured = sum(nll.get(f"box_unmeasured_{n}", 0) for n in ("vehicle", "bicyclist"))
    if unmeasured:
        lines.append("")
        lines.append(f"{unmeasured} scored actors had no measured box size: their box term is "
                     f"left out of the NLL; {report['realism']['real']['boxes_unmeasured']} "
                     "of the real scenes' boxes above are placeholders (overlaps, area MMD "
                     "without them)")
    by_source = report.get("nll_by_source") or {}
    if len(by_source) > 1:
        lines.append("")
        lines.append("SceneGen NLL by source | scenes | NLL/scene | NLL/actor")
        for name, r in by_source.items():
            lines.append(
                f"{name} | {r['scenes']} | {r['scene_nll']:.1f} | {r['nll_per_actor']:.2f}"
            )
    return "\n".join(lines)


def _with_interval(value, interval) -> str:
    if value is None:
        return "-"
    if not interval:
        return f"{value:.4f}"
    return f"{value:.4f} ({interval[0]:.4f}-{interval[1]:.4f})"


def _share(x) -> str:
    return "-" if x is None else f"{x:.1%}"


def _degrees(x) -> str:
    return "-" if x is None else f"{x:.1f} deg"
