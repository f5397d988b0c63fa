"""Paired comparison of two models scored on the same scenes, with block-bootstrap intervals.

Input: the per-step terms that `scenegen score --actors-out F.npz` writes. The statistic is
the difference in NLL per actor (model A minus model B) of one term, over the actors of one
class or of all classes: sum over scenes of (A's NLL - B's NLL) / number of actors. Several
A/B pairs (seeds) are averaged scene by scene before the ratio. The interval resamples blocks
of consecutive scenes (frames of one log are correlated) with replacement.
"""

from __future__ import annotations

import zipfile

import numpy as np

from scenegen_jax.distributions import TERMS
from scenegen_jax.eval.nll import actor_steps, box_scored
from scenegen_jax.scene import CLASS_NAMES

FIELDS = (*TERMS, "step_valid", "step_cls")
# Files written before scores recorded which boxes were measured lack it: all were.
OPTIONAL_FIELDS = ("step_size_measured",)


def load_scores(path: str) -> dict[str, np.ndarray]:
    """The arrays of a `--actors-out` file (never unpickles); errors name the file and field:
    a file that is no .npz of plain arrays, a missing field, fields of other shapes than
    `step_valid`, or an NLL that is NaN or inf at an actor's step."""
    not_npz = f"{path}: not a `score --actors-out` .npz"
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a .npy: one array
            raise TypeError(f"one {loaded.dtype} array of shape {loaded.shape}")
        with loaded as f:  # object arrays fail here, as they are read
            scores = {k: f[k] for k in (*FIELDS, *OPTIONAL_FIELDS) if k in f.files}
    except (ValueError, TypeError, zipfile.BadZipFile) as e:  # pickled data, not a zip
        raise ValueError(f"{not_npz} ({e})") from e
    missing = [k for k in FIELDS if k not in scores]
    if missing:
        raise ValueError(f"{path}: missing field {missing[0]!r} (not a --actors-out file?)")
    shape = scores["step_valid"].shape
    for k in scores:
        if scores[k].shape != shape:
            raise ValueError(f"{path}: field {k!r}: shape {scores[k].shape}, step_valid's "
                             f"is {shape}")
    actor = actor_steps(scores)
    for k in TERMS:
        if not np.all(np.isfinite(scores[k][actor])):
            raise ValueError(f"{path}: field {k!r}: NaN or inf at an actor's step")
    return scores


def actor_sums(scores: dict, term: str, cls: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Per scene: (sum of `term` NLL over its actors of class `cls`, their count) [S] each;
    cls None takes every class (not the stop token). term "total" sums all terms; the box
    term counts only the actors whose box was scored (`nll.box_scored`)."""
    if term != "total" and term not in TERMS:
        raise ValueError(f"term {term!r}: expected 'total' or one of {TERMS}")
    values = sum(scores[k] for k in TERMS) if term == "total" else scores[term]
    actor = box_scored(scores) if term == "box" else actor_steps(scores)
    if cls is not None:
        actor = actor & (scores["step_cls"] == cls)
    return np.where(actor, values, 0.0).sum(1), actor.sum(1)


def _check_same_scenes(runs: list[dict], names: list[str]) -> None:
    for run, name in zip(runs[1:], names[1:], strict=True):
        for k in ("step_valid", "step_cls"):
            if run[k].shape != runs[0][k].shape or not np.array_equal(run[k], runs[0][k]):
                raise ValueError(
                    f"{name}: field {k!r} differs from {names[0]}'s: not the same scenes"
                )


def paired_difference(
    a: list[dict],
    b: list[dict],
    term: str = "location",
    cls: int | None = None,
    block: int = 10,
    samples: int = 2000,
    seed: int = 0,
) -> dict:
    """NLL per actor of A minus B, pairs averaged scene by scene, with a 95% interval.

    Returns dict(diff, low, high, actors): the point estimate, the 2.5% and 97.5% percentiles
    of `samples` block-bootstrap resamples (blocks of `block` consecutive scenes; None when
    the scenes make a single block), and the number of actors counted.
    """
    if len(a) != len(b) or not a:
        raise ValueError(f"need as many A runs as B runs, at least one (got {len(a)}, {len(b)})")
    for name, value, least in (("block", block, 1), ("samples", samples, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"--{name}: expected an integer >= {least}, got {value!r}")
    d = np.mean(
        [
            actor_sums(x, term, cls)[0] - actor_sums(y, term, cls)[0]
            for x, y in zip(a, b, strict=True)
        ],
        axis=0,
    )
    n = actor_sums(a[0], term, cls)[1]
    if n.sum() == 0:
        return {"diff": None, "low": None, "high": None, "actors": 0}
    starts = np.arange(0, len(d), block)
    if len(starts) < 2:  # resampling one block always gives the estimate itself
        return {"diff": float(d.sum() / n.sum()), "low": None, "high": None,
                "actors": int(n.sum())}
    d_blocks = np.add.reduceat(d, starts)
    n_blocks = np.add.reduceat(n, starts)
    pick = np.random.default_rng(seed).integers(0, len(starts), (samples, len(starts)))
    stats = d_blocks[pick].sum(1) / np.maximum(n_blocks[pick].sum(1), 1)
    low, high = np.percentile(stats, [2.5, 97.5])
    return {
        "diff": float(d.sum() / n.sum()),
        "low": float(low),
        "high": float(high),
        "actors": int(n.sum()),
    }


def compare_files(
    a_paths: list[str],
    b_paths: list[str],
    term: str = "location",
    block: int = 10,
    samples: int = 2000,
    seed: int = 0,
) -> dict:
    """`paired_difference` per class and over all actors for `--actors-out` files."""
    a = [load_scores(p) for p in a_paths]
    b = [load_scores(p) for p in b_paths]
    _check_same_scenes(a + b, list(a_paths) + list(b_paths))
    rows = {
        name: paired_difference(a, b, term, c, block, samples, seed)
        for c, name in enumerate(CLASS_NAMES)
    }
    rows["all actors"] = paired_difference(a, b, term, None, block, samples, seed)
    return {
        "a": list(a_paths),
        "b": list(b_paths),
        "term": term,
        "block": block,
        "samples": samples,
        "rows": rows,
    }
