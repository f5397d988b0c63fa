"""Scene NLLs and logged statistics from the unroll's per-step log-likelihood terms."""

from __future__ import annotations

import jax.numpy as jnp

from scenegen_jax.distributions import TERMS
from scenegen_jax.scene import CLASS_NAMES, STOP, VEHICLE

# Terms logged per vehicle (the learning curves of the attributes).
VEHICLE_TERMS = ("location", "box", "heading", "velocity")


def step_size_measured(actors, steps: int):
    """[B, steps] bool: whether step t's actor (actor t of canonically ordered actors [B, N],
    N <= steps) had a measured box size (`Actors.size_measured`); the steps past its slots
    (the stop token, padding) count as measured."""
    measured = actors.size_measured
    if measured is None:
        return jnp.ones((actors.cls.shape[0], steps), bool)
    return jnp.pad(measured, [(0, 0), (0, steps - measured.shape[1])], constant_values=True)


def nll_metrics(terms: dict, step_valid, step_cls, step_measured=None) -> tuple[jnp.ndarray, dict]:
    """Scene NLLs [B] and summed statistics for logging (sums and counts, not means);
    `step_measured` (`step_size_measured`) counts the vehicles whose box term is scored."""
    total = sum(terms[k] for k in TERMS)  # [B, T] log-likelihood per step
    scene_nll = -jnp.sum(total, axis=1)
    stats = {f"nll_{k}": -jnp.sum(terms[k]) for k in TERMS}
    for c, name in enumerate(CLASS_NAMES):
        m = step_valid & (step_cls == c)
        stats[f"nll_sum_{name}"] = -jnp.sum(jnp.where(m, total, 0.0))
        stats[f"count_{name}"] = jnp.sum(m)
    vehicle = step_valid & (step_cls == VEHICLE)
    for k in VEHICLE_TERMS:
        stats[f"nll_{k}_sum_vehicle"] = -jnp.sum(jnp.where(vehicle, terms[k], 0.0))
    measured = vehicle if step_measured is None else vehicle & step_measured
    stats["count_box_vehicle"] = jnp.sum(measured)
    stats["nll_sum_stop"] = -jnp.sum(jnp.where(step_cls == STOP, total, 0.0) * step_valid)
    stats["scenes"] = jnp.asarray(scene_nll.shape[0])
    return scene_nll, stats


def mean_nll(unrolled, actors=None) -> tuple[jnp.ndarray, dict]:
    """The loss, mean scene NLL (nats), and stats from (terms, step_valid, step_cls) and the
    unrolled scenes' actors (for the count of measured boxes; None: all measured)."""
    terms, step_valid, step_cls = unrolled
    measured = None if actors is None else step_size_measured(actors, step_cls.shape[1])
    scene_nll, stats = nll_metrics(terms, step_valid, step_cls, measured)
    return jnp.mean(scene_nll), stats
