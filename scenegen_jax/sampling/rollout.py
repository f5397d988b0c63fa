"""Autoregressive sampling of traffic scenes (paper sec. 3.3, SPEC sec. 6), jitted and vmapped.

`rollout` generates ONE scene (unbatched) inside a single traced function: step 0 (from the
zero ConvLSTM state, whose recurrent convolutions it skips), then a `lax.while_loop` over the
remaining steps, at most `cfg.max_actors` in all, whose carry (`SamplerState`) holds the
ConvLSTM state, the actor raster, the actors so far, the previous bin and a done flag. No host
transfer, no Python loop over steps. The loop exits as soon as the scene is done; under `vmap`
it runs until every scene of the batch is done and finished scenes are left unchanged
(`lax.while_loop`'s batching rule selects their old carry), so a batched call returns exactly
the per-scene results. `sample_batch` / `sample_scenes` map it over scenes and keys,
`parallel` scenes vmapped at a time (on CPU one at a time, the fastest there), and
`sample_split` / `sample_scenes` split a batch into `workers` concurrent `sample_batch` calls
(`scenegen_jax.concurrency`; on CPU one per core).

One step t (key `fold_in(key, t)`):
  1. Input gates = map gates (computed once per scene before the loop: the map is constant)
     + actor gates of the current actor raster (carried, and updated after each step by a
     convolution over the new actor's drawing window only: `SceneGenNet.next_actor_gates`);
     ConvLSTM step; backbone features.
  2. Class from the categorical over (vehicle, pedestrian, bicyclist, stop); classes at their
     cap get zero mass. STOP ends the scene.
  3. Location: the class's logits masked to bins >= the previous actor's bin (canonical
     order, ties allowed) and renormalised; no allowed bin ends the scene.
  4. Candidates: R = `candidates` i.i.d. (bin, uniform position in the bin, attributes) draws.
     Attributes come from the class's MLP at the bin's feature vector; box size, heading and
     velocity are each the most likely of M = `proposals` draws (best-of-M; M = 1 is plain
     sampling). Pedestrians: nominal square box (`cfg.pedestrian_size_m`), heading = the
     velocity direction (0 when standing); their box and heading are not modelled.
  5. Collision rejection: a vehicle or bicyclist candidate whose box overlaps the ego or an
     earlier vehicle/bicyclist box is rejected; the first accepted candidate is kept. The first
     round of candidates is exact rejection sampling (the first acceptance in an i.i.d.
     sequence); when all R fail, their bins are masked out and another round is drawn, at
     most `rounds` rounds; if none is accepted (or no bin is left), the scene stops. So the
     output never holds overlapping vehicle/bicyclist boxes.
  6. The actor is written to slot t and drawn into the actor raster for the next step.

Given actors (conditioning, beyond the paper): the first `n_given` steps are teacher forced
on the valid given actors in canonical order (the model runs, nothing is sampled), then
sampling continues with the ordering mask after the last given actor. Given actors appear
unchanged in the leading slots of the output; they are not collision-tested among
themselves, but sampled boxes are tested against theirs. Class caps count given actors too.

Numerical guards (sampled actors only; given actors are taken as they are): box width and
length are clamped to [`MIN_SIZE_M`, `MAX_SIZE_M`] (20 m: the largest box the actor raster
draws unclipped), speed to at most `MAX_SPEED_MPS`, and any non-finite value from a diverged
model is replaced (size -> `MIN_SIZE_M`, heading and velocity -> 0), so samples never hold NaN.
Positions are strictly inside their bin, hence inside the region.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from scenegen_jax.concurrency import concurrent_map, default_workers
from scenegen_jax.config import Config
from scenegen_jax.distributions import (
    box_proposal_score,
    heading_log_prob,
    is_relative_direction,
    masked_log_softmax,
    ordering_mask,
    sample_bins,
    sample_box,
    sample_class,
    sample_heading,
    sample_velocity,
    velocity_proposal_score,
)
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.raster.actors import draw_actor, empty_actor_raster
from scenegen_jax.sampling.geometry import collides
from scenegen_jax.scene import (
    NUM_CLASSES,
    PEDESTRIAN,
    STOP,
    Actors,
    bin_center,
    bin_index,
    canonical_order,
    empty_actors,
    wrap_angle,
)

MIN_SIZE_M = 0.2
MAX_SIZE_M = 20.0
MAX_SPEED_MPS = 50.0
DEFAULT_CANDIDATES = 8
DEFAULT_ROUNDS = 4
# The steps whose location distributions the paper's Figure 7 shows.
HEATMAP_STEPS = (0, 5, 10, 15, 20)
# Positions stay this fraction of a bin inside it (as in `distributions.sample_location`).
_EDGE = 1e-4

# Why a scene ended (`Sample.stop_reason`).
STOP_TOKEN, FULL, NO_BIN, COLLISION = 0, 1, 2, 3
STOP_REASONS = ("stop_token", "full", "no_bin", "collision")


class Model(Protocol):
    """What the sampler needs from a network; every method takes the params first.

    Arrays carry a leading batch axis of 1 (the rollout is unbatched). The recurrent state is
    an opaque PyTree. `scenegen_jax.sampling.rollout.NetworkModel` wraps `SceneGenNet`; tests
    substitute a fake with known outputs.
    """

    def initial_state(self, params: Any) -> Any: ...
    def map_gates(self, params: Any, map_raster: jnp.ndarray) -> jnp.ndarray: ...
    def actor_gates(self, params: Any, actor_raster: jnp.ndarray) -> jnp.ndarray: ...
    def next_actor_gates(self, params: Any, gates: jnp.ndarray, before: jnp.ndarray,
                         after: jnp.ndarray, position: jnp.ndarray) -> jnp.ndarray: ...
    def recur(self, params: Any, state: Any, gates: jnp.ndarray) -> tuple[Any, jnp.ndarray]:
        """One recurrent step; state None is `initial_state` (the first step)."""
    def features(self, params: Any, h: jnp.ndarray) -> jnp.ndarray: ...
    def class_logits(self, params: Any, f: jnp.ndarray) -> jnp.ndarray: ...
    def location_logits(self, params: Any, f: jnp.ndarray, cls: jnp.ndarray) -> jnp.ndarray: ...
    def attributes(self, params: Any, feat: jnp.ndarray, cls: jnp.ndarray) -> tuple: ...


@dataclasses.dataclass(frozen=True)
class NetworkModel:
    """`Model` backed by `SceneGenNet` (hashable: usable as a static jit argument).

    single_example: the location head as plain convolutions with the class's kernels
    (XLA:CPU's fastest for one scene; under vmap they become a grouped convolution, slow on
    CPU) instead of `conv_per_example`; the same values either way.
    """

    cfg: Config
    single_example: bool = True

    def _apply(self, params, method, *args):
        return SceneGenNet(self.cfg).apply({"params": params}, *args, method=method)

    def initial_state(self, params):
        return self._apply(params, SceneGenNet.initial_state, 1)

    def map_gates(self, params, map_raster):
        return self._apply(params, SceneGenNet.map_gates, map_raster)

    def actor_gates(self, params, actor_raster):
        return self._apply(params, SceneGenNet.actor_gates, actor_raster)

    def next_actor_gates(self, params, gates, before, after, position):
        return self._apply(params, SceneGenNet.next_actor_gates, gates, before, after, position)

    def recur(self, params, state, gates):
        return self._apply(params, SceneGenNet.recur, state, gates)

    def features(self, params, h):
        return self._apply(params, SceneGenNet.features, h)

    def class_logits(self, params, f):
        return self._apply(params, SceneGenNet.class_logits, f)

    def location_logits(self, params, f, cls):
        return self._apply(params, SceneGenNet.location_logits, f, cls, self.single_example)

    def attributes(self, params, feat, cls):
        return self._apply(params, SceneGenNet.attributes, feat, cls)


@struct.dataclass
class SamplerState:
    """Carry of the rollout loop (one scene).

    Attributes:
      lstm: recurrent state of the model (for SceneGenNet ((h1, c1), (h2, c2)), [1, H, W, h]).
      raster: float32 [H, W, 9] actor raster of the ego and the actors so far.
      actor_gates: the model's actor share of layer 1's input gates for `raster`
        ([1, H, W, 4h] for SceneGenNet), updated locally as each actor is drawn.
      actors: Actors [N], slots < count filled in canonical order.
      count: int32 [] actors placed; also the step index (each step places one or ends).
      prev_bin: int32 [] bin of the last actor (0 before the first).
      done: bool [] the scene has ended.
      class_counts: int32 [3] actors per class so far (given ones included).
      stop_reason: int32 [] one of STOP_TOKEN, FULL, NO_BIN, COLLISION (valid when done).
      rejected: int32 [] candidates rejected for collisions so far.
      heatmaps: float32 [Sh, H*W] location distributions recorded at `heatmap_steps`.
      heatmap_cls: int32 [Sh] class of each recorded distribution (-1: step not reached,
        STOP: the scene stopped there).
    """

    lstm: Any
    raster: jnp.ndarray
    actor_gates: jnp.ndarray
    actors: Actors
    count: jnp.ndarray
    prev_bin: jnp.ndarray
    done: jnp.ndarray
    class_counts: jnp.ndarray
    stop_reason: jnp.ndarray
    rejected: jnp.ndarray
    heatmaps: jnp.ndarray
    heatmap_cls: jnp.ndarray


@struct.dataclass
class Sample:
    """One sampled scene (add leading axes for batches).

    Attributes:
      actors: Actors [N]: the given actors first (unchanged), then the sampled ones; valid
        slots first, in canonical order.
      num_given: int32 [] given actors inserted.
      stop_reason: int32 [] why the scene ended (`STOP_REASONS`).
      rejected: int32 [] candidate draws rejected for collisions.
      heatmaps: float32 [Sh, H*W] location probabilities (ordering-masked, renormalised)
        of the step's class at each of `heatmap_steps` (zeros where not reached / stopped).
      heatmap_cls: int32 [Sh] class of each heatmap (-1 not reached, 3 the scene stopped).
    """

    actors: Actors
    num_given: jnp.ndarray
    stop_reason: jnp.ndarray
    rejected: jnp.ndarray
    heatmaps: jnp.ndarray
    heatmap_cls: jnp.ndarray


def _where(cond, x, y):
    return jax.tree.map(lambda a, b: jnp.where(cond, a, b), x, y)


def _take(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def sample_attributes(
    keys: jax.Array,
    box_raw: jnp.ndarray,
    heading_raw: jnp.ndarray,
    velocity_raw: jnp.ndarray,
    cls: jnp.ndarray,
    cfg: Config,
    proposals: int,
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Box size, heading and velocity of R actors, each the most likely of M draws.

    Best-of-M (paper sec. 3.3): M proposals per attribute, keep the most likely under its own
    mixture (NaN never wins, ties keep the first), with densities in the mixtures' own
    coordinates: (log width, log length) for boxes (`box_proposal_score`) and (log speed,
    direction) for velocities (`velocity_proposal_score`). Planar densities would carry the
    Jacobians 1 / (w l) and 1 / s^2 and make the smallest box and the slowest speed win (with
    M = 10 every sampled speed fell below 1 m/s). Whether an actor stands is drawn once, by its
    first velocity proposal (probability pi_0, a probability that is not compared with
    densities); a moving actor keeps the best of its moving proposals. The velocity is drawn
    given the chosen heading (its direction is relative to it for vehicles and bicyclists).
    This is `distributions.best_of_m` with the R x M draws flattened into one vmap: nesting
    a vmap over M inside the vmap over candidates doubled XLA:CPU's compile time of the
    rollout. Keys: actor r splits keys[r] into (box, heading, velocity) keys,
    each split into M proposal keys. With M = 1 the single draw is kept (plain sampling).

    Pedestrians get the nominal square box (`cfg.pedestrian_size_m`) and the velocity
    direction as heading (0 when standing). Outputs are clamped and made finite (see the
    module docstring).

    Args:
      keys: [R] PRNG keys.
      box_raw, heading_raw, velocity_raw: [R, ...] raw head outputs of each actor's class.
      cls: int32 [R] classes (vehicle, pedestrian or bicyclist).
      cfg: config (zero_speed, pedestrian_size_m).
      proposals: M >= 1 (static).

    Returns:
      (size [R, 2] (width, length) m, heading [R] rad in [0, 2pi), velocity [R, 2] m/s).
    """
    if proposals < 1:
        raise ValueError(f"best-of-M needs M >= 1, got {proposals}")
    r, m = keys.shape[0], proposals
    sub = jax.vmap(lambda k: jax.random.split(k, 3))(keys)  # [R, 3]

    def proposal_keys(k):  # [R] -> [R * M]
        return jax.vmap(lambda kk: jax.random.split(kk, m))(k).reshape(r * m)

    def flat(x):  # [R, ...] -> [R * M, ...], proposals of one actor adjacent
        return jnp.repeat(x, m, axis=0)

    def best(draws, log_probs):  # keeps the most likely of each actor's M draws
        if m == 1:
            return draws
        lp = jnp.where(jnp.isnan(log_probs), -jnp.inf, log_probs).reshape(r, m)
        return draws[jnp.arange(r) * m + jnp.argmax(lp, axis=1)]

    boxes = jax.vmap(sample_box)(proposal_keys(sub[:, 0]), flat(box_raw))
    lp = jax.vmap(box_proposal_score)(flat(box_raw), boxes) if m > 1 else None
    size = best(boxes, lp)
    heads = jax.vmap(sample_heading)(proposal_keys(sub[:, 1]), flat(heading_raw))
    lp = jax.vmap(heading_log_prob)(flat(heading_raw), heads) if m > 1 else None
    heading = jnp.nan_to_num(best(heads, lp), nan=0.0, posinf=0.0, neginf=0.0)

    relative = is_relative_direction(cls)
    zero = cfg.zero_speed
    vels = jax.vmap(lambda k, raw, h, rel: sample_velocity(k, raw, h, rel, zero))(
        proposal_keys(sub[:, 2]), flat(velocity_raw), flat(heading), flat(relative))
    lp = None
    if m > 1:
        score = jax.vmap(lambda raw, v, h, rel: velocity_proposal_score(raw, v, h, rel, zero))(
            flat(velocity_raw), vels, flat(heading), flat(relative)).reshape(r, m)
        moving = (jnp.sum(vels * vels, axis=-1) > zero * zero).reshape(r, m)
        first = jnp.arange(m) == 0
        lp = jnp.where(moving[:, :1], jnp.where(moving, score, -jnp.inf),
                       jnp.where(first, 0.0, -jnp.inf)).reshape(r * m)
    velocity = jnp.nan_to_num(best(vels, lp), nan=0.0, posinf=0.0, neginf=0.0)

    speed = jnp.sqrt(jnp.sum(velocity**2, axis=-1))
    velocity = velocity * jnp.minimum(1.0, MAX_SPEED_MPS / jnp.maximum(speed, 1e-12))[:, None]
    size = jnp.clip(jnp.nan_to_num(size, nan=MIN_SIZE_M), MIN_SIZE_M, MAX_SIZE_M)
    is_ped = cls == PEDESTRIAN
    moving = speed > zero
    walk = jnp.arctan2(velocity[:, 1], jnp.where(moving, velocity[:, 0], 1.0))
    size = jnp.where(is_ped[:, None], jnp.asarray(cfg.pedestrian_size_m, size.dtype), size)
    heading = wrap_angle(jnp.where(is_ped, jnp.where(moving, walk, 0.0), heading))
    # float32 mod can round up to exactly 2pi; keep the documented [0, 2pi).
    heading = jnp.where(heading >= 2 * jnp.pi, 0.0, heading)
    return size.astype(jnp.float32), heading.astype(jnp.float32), velocity.astype(jnp.float32)


def _candidates(key, params, model: Model, f, cls, log_probs, cfg: Config, proposals, count):
    """`count` i.i.d. candidate actors of class `cls`: bins from `log_probs` [H*W] (-inf
    outside the allowed set), positions uniform in the bins, best-of-M attributes."""
    k_bin, k_pos, k_attr = jax.random.split(key, 3)
    bins = sample_bins(k_bin, log_probs, count, cfg.grid_size)
    u = jax.random.uniform(k_pos, (count, 2), minval=_EDGE, maxval=1.0 - _EDGE)
    position = bin_center(bins, cfg) + (u - 0.5) * cfg.m_per_px
    feat = f[0].reshape(-1, f.shape[-1])[bins]  # [R, hidden]
    classes = jnp.full((count,), cls, jnp.int32)
    box_raw, heading_raw, velocity_raw = model.attributes(params, feat, classes)
    size, heading, velocity = sample_attributes(
        jax.random.split(k_attr, count), box_raw, heading_raw, velocity_raw, classes, cfg,
        proposals)
    return bins, Actors(
        cls=classes,
        position=position.astype(jnp.float32),
        size=size,
        heading=heading,
        velocity=velocity,
        valid=jnp.ones((count,), bool),
    )


def _place(key, params, model: Model, f, cls, log_probs, state: SamplerState, ego: Actors,
           cfg: Config, proposals: int, candidates: int, rounds: int):
    """Draws candidates round by round until one is collision-free (see module docstring).

    Returns:
      (actor, found, rejected): the first accepted candidate (any candidate if none), whether
      one was accepted, and how many candidates were rejected.
    """
    boxed = cls != PEDESTRIAN
    n_bins = log_probs.shape[0]

    def draw(r, banned):
        lp = jnp.where(banned, -jnp.inf, log_probs)
        any_left = jnp.any(jnp.isfinite(lp))
        lp = jnp.where(any_left, lp, 0.0)  # keeps the categorical finite; result unused then
        bins, cands = _candidates(jax.random.fold_in(key, r), params, model, f, cls, lp, cfg,
                                  proposals, candidates)
        hit = jax.vmap(collides, in_axes=(0, None, None))(cands, state.actors, ego)
        ok = any_left & jnp.logical_not(boxed & hit)
        return bins, cands, ok, any_left

    def cond(c):
        r, _, found, any_left, *_ = c
        return (r < rounds) & jnp.logical_not(found) & any_left

    def body(c):
        r, banned, _, _, _, rejected = c
        bins, cands, ok, any_left = draw(r, banned)
        first = jnp.argmax(ok)  # the first accepted candidate (0 if none)
        found = jnp.any(ok)
        # Rejections before the accepted one (all R if none was accepted).
        n_rejected = jnp.where(found, first, jnp.where(any_left, candidates, 0))
        tried = jnp.zeros((n_bins,), bool).at[bins].set(True)
        banned = banned | (tried & jnp.logical_not(found))
        left = jnp.any(jnp.isfinite(jnp.where(banned, -jnp.inf, log_probs)))
        return r + 1, banned, found, left, _take(cands, first), rejected + n_rejected

    any_valid = jnp.any(jnp.isfinite(log_probs))
    init = (
        jnp.int32(0),
        jnp.zeros((n_bins,), bool),
        jnp.bool_(False),
        any_valid,
        _take(empty_actors(1), 0),
        jnp.int32(0),
    )
    init = jax.tree.map(jnp.asarray, init)
    _, _, found, _, actor, rejected = lax.while_loop(cond, body, init)
    return actor, found, rejected


def _pad_given(given: Actors | None, n: int) -> Actors:
    """Given actors padded (or created empty) to n slots; raises if more than n slots."""
    if given is None:
        return jax.tree.map(jnp.asarray, empty_actors(n))
    slots = given.cls.shape[0]
    if slots > n:
        raise ValueError(f"given actors: {slots} slots, more than max_actors = {n}")
    return jax.tree.map(
        lambda x: jnp.pad(jnp.asarray(x), [(0, n - slots)] + [(0, 0)] * (jnp.ndim(x) - 1)), given
    )


def rollout(
    key: jax.Array,
    params: Any,
    map_raster: jnp.ndarray,
    ego: Actors,
    cfg: Config,
    given: Actors | None = None,
    caps: jnp.ndarray | None = None,
    *,
    proposals: int | None = None,
    candidates: int = DEFAULT_CANDIDATES,
    rounds: int = DEFAULT_ROUNDS,
    heatmap_steps: tuple[int, ...] = (),
    model: Model | None = None,
) -> Sample:
    """Samples one scene (unbatched; jit and vmap outside, see `sample_batch`).

    Args:
      key: PRNG key; step t uses fold_in(key, t), so a key reproduces the scene bit for bit.
      params: network parameters (or whatever `model` takes).
      map_raster: float32 [H, W, Cm] map channels, already cropped to the grid.
      ego: the ego (Actors without a leading axis).
      cfg: config (grid, max_actors N, proposals, zero_speed, pedestrian_size_m).
      given: optional Actors [G <= N] to condition on, inside the region with valid values
        (validate on the host, e.g. `Scene.validate` or `export.actors_from_records`); they
        are put in canonical order (a no-op when they already are).
      caps: optional int32 [3] maximum actors per class (given ones count); default N.
      proposals: M of best-of-M (static); default cfg.proposals.
      candidates: R, candidate draws per rejection round (static).
      rounds: rejection rounds before the scene stops (static).
      heatmap_steps: steps whose location distribution is recorded (static).
      model: the network interface; default `NetworkModel(cfg)`.

    Returns:
      Sample.
    """
    model = NetworkModel(cfg) if model is None else model
    m = cfg.proposals if proposals is None else proposals
    n = cfg.max_actors
    n_bins = cfg.grid_size * cfg.grid_size
    # Stable sort: canonical input is unchanged, anything else is put in canonical order.
    given = canonical_order(_pad_given(given, n), cfg)
    n_given = jnp.sum(given.valid).astype(jnp.int32)
    caps = jnp.full((NUM_CLASSES,), n, jnp.int32) if caps is None else jnp.asarray(caps, jnp.int32)
    steps = jnp.asarray(heatmap_steps, jnp.int32).reshape(-1)
    ego = jax.tree.map(jnp.asarray, ego)

    map_gates = model.map_gates(params, jnp.asarray(map_raster, jnp.float32)[None])
    raster = draw_actor(empty_actor_raster(cfg), ego, True, cfg)

    def step(state: SamplerState, first: bool = False) -> SamplerState:
        t = state.count
        k_class, k_place = jax.random.split(jax.random.fold_in(key, t))
        gates = map_gates + state.actor_gates
        lstm, h = model.recur(params, None if first else state.lstm, gates)
        f = model.features(params, h)

        logits = model.class_logits(params, f)[0]
        full_class = state.class_counts >= caps
        logits = logits.at[:NUM_CLASSES].set(jnp.where(full_class, -jnp.inf, logits[:NUM_CLASSES]))
        forced = t < n_given
        g = _take(given, jnp.minimum(t, n - 1))
        cls = jnp.where(forced, g.cls, sample_class(k_class, logits)).astype(jnp.int32)
        is_stop = cls == STOP
        safe_cls = jnp.where(is_stop, 0, cls)

        loc = model.location_logits(params, f, safe_cls[None])[0]
        log_probs, _ = masked_log_softmax(loc, ordering_mask(state.prev_bin, n_bins))
        # Bins allowed by the mask but with -inf logits give NaN in the softmax; drop them.
        log_probs = jnp.where(jnp.isnan(log_probs), -jnp.inf, log_probs)
        any_valid = jnp.any(jnp.isfinite(log_probs))
        # Forced and stop steps draw no candidates (no allowed bin: the round loop is skipped).
        place_lp = jnp.where(forced | is_stop, -jnp.inf, log_probs)
        sampled, found, rejected = _place(k_place, params, model, f, safe_cls, place_lp, state,
                                          ego, cfg, m, candidates, rounds)
        actor = _where(forced, g.replace(valid=jnp.bool_(True)), sampled)
        placed = forced | (jnp.logical_not(is_stop) & any_valid & found)
        actor = actor.replace(valid=placed)

        actors = jax.tree.map(lambda a, x: a.at[t].set(x), state.actors, actor)
        count = t + placed.astype(jnp.int32)
        done = jnp.logical_not(placed) | (count >= n)
        reason = jnp.select(
            [placed, is_stop, jnp.logical_not(any_valid)], [FULL, STOP_TOKEN, NO_BIN], COLLISION
        ).astype(jnp.int32)
        hit = steps == t
        probs = jnp.where(is_stop, 0.0, jnp.exp(log_probs))
        heatmaps = jnp.where(hit[:, None], probs[None], state.heatmaps)
        heatmap_cls = jnp.where(hit, cls, state.heatmap_cls)
        raster = draw_actor(state.raster, actor, False, cfg)
        return SamplerState(
            lstm=lstm,
            raster=raster,
            actor_gates=model.next_actor_gates(params, state.actor_gates, state.raster[None],
                                               raster[None], actor.position[None]),
            actors=actors,
            count=count,
            prev_bin=jnp.where(placed, bin_index(actor.position, cfg), state.prev_bin),
            done=done,
            class_counts=state.class_counts + (jnp.arange(NUM_CLASSES) == cls) * placed,
            stop_reason=jnp.where(done, reason, state.stop_reason),
            rejected=state.rejected + rejected,
            heatmaps=heatmaps,
            heatmap_cls=heatmap_cls,
        )

    init = SamplerState(
        lstm=model.initial_state(params),
        raster=raster,
        actor_gates=model.actor_gates(params, raster[None]),
        actors=jax.tree.map(jnp.asarray, empty_actors(n)),
        count=jnp.int32(0),
        prev_bin=jnp.int32(0),
        done=jnp.bool_(n == 0),
        class_counts=jnp.zeros((NUM_CLASSES,), jnp.int32),
        stop_reason=jnp.int32(FULL),
        rejected=jnp.int32(0),
        heatmaps=jnp.zeros((steps.shape[0], n_bins), jnp.float32),
        heatmap_cls=jnp.full((steps.shape[0],), -1, jnp.int32),
    )
    if n > 0:  # step 0 before the loop: from the zero state, without its convolutions
        init = step(init, first=True)
    final = lax.while_loop(lambda s: jnp.logical_not(s.done), step, init)
    return Sample(
        actors=final.actors,
        num_given=jnp.minimum(n_given, final.count),
        stop_reason=final.stop_reason,
        rejected=final.rejected,
        heatmaps=final.heatmaps,
        heatmap_cls=final.heatmap_cls,
    )


@functools.partial(
    jax.jit,
    static_argnames=("cfg", "proposals", "candidates", "rounds", "heatmap_steps", "model",
                     "parallel"),
)
def sample_batch(
    keys: jax.Array,
    params: Any,
    maps: jnp.ndarray,
    egos: Actors,
    given: Actors,
    caps: jnp.ndarray,
    *,
    cfg: Config,
    proposals: int | None = None,
    candidates: int = DEFAULT_CANDIDATES,
    rounds: int = DEFAULT_ROUNDS,
    heatmap_steps: tuple[int, ...] = (),
    model: Model | None = None,
    parallel: int | None = None,
) -> Sample:
    """One compiled call for a batch: scene b is `rollout(keys[b], params, maps[b], ...)`.

    The B x S scenes run `parallel` at a time under vmap (`lax.map` over groups); a vmapped
    group runs until its longest scene is done. With parallel = 1 each scene runs on its own
    (no vmap), which is fastest on CPU: there a vmapped group's activations leave the cache
    and its convolutions slow down more than batching gains (bench/README.md).

    Args:
      keys: [B, S] keys; S samples per map share its map, ego, given actors and caps.
      params: network parameters.
      maps: float32 [B, H, W, Cm].
      egos: Actors [B].
      given: Actors [B, N] (all invalid for none).
      caps: int32 [B, 3].
      cfg, proposals, candidates, rounds, heatmap_steps, model: as in `rollout` (static).
      parallel: scenes vmapped together (static); default `default_parallel()`.

    Returns:
      Sample with leading axes [B, S].
    """

    def one(key, map_raster, ego, g, c):
        return rollout(key, params, map_raster, ego, cfg, g, c, proposals=proposals,
                       candidates=candidates, rounds=rounds, heatmap_steps=heatmap_steps,
                       model=model)

    b, s = keys.shape[:2]
    parallel = default_parallel() if parallel is None else parallel
    if parallel < 1:
        raise ValueError(f"parallel must be >= 1, got {parallel}")
    if model is None:
        model = NetworkModel(cfg, single_example=parallel == 1)
    if parallel >= b * s:
        per_map = jax.vmap(one, in_axes=(0, None, None, None, None))
        return jax.vmap(per_map)(keys, maps, egos, given, caps)

    impl = jax.random.key_impl(keys)

    def flat(x):  # scene (b, s) -> index b * S + s
        key, i = x
        key = jax.random.wrap_key_data(key, impl=impl)
        return one(key, maps[i], _take(egos, i), _take(given, i), caps[i])

    # Groups of `parallel` scenes; the last group is padded with copies of the last scene.
    n = b * s
    groups = -(-n // parallel)
    scene = jnp.minimum(jnp.arange(groups * parallel, dtype=jnp.int32), n - 1)
    data = jax.random.key_data(keys)  # raw key data: typed keys do not pass through lax.map
    data = data.reshape(n, *data.shape[2:])[scene]
    if parallel == 1:
        out, lead = lax.map(flat, (data, scene // s)), 1
    else:
        grouped = (data.reshape(groups, parallel, *data.shape[1:]),
                   (scene // s).reshape(groups, parallel))
        out, lead = lax.map(jax.vmap(flat), grouped), 2

    def unflat(x):  # [groups (, parallel), ...] -> [B, S, ...]
        rest = x.shape[lead:]
        return x.reshape(groups * parallel, *rest)[:n].reshape(b, s, *rest)

    return jax.tree.map(unflat, out)


def default_parallel() -> int:
    """Scenes `sample_batch` vmaps together by default: 1 on CPU, all on accelerators."""
    return 1 if jax.default_backend() == "cpu" else 2**31 - 1


def sample_split(keys: jax.Array, params: Any, maps, egos: Actors, given: Actors, caps, *,
                 workers: int | None = None, **kwargs) -> Sample:
    """`sample_batch(keys, params, maps, egos, given, caps, **kwargs)` as `workers`
    concurrent calls on equal parts of the batch (`concurrency.concurrent_map`); each scene
    depends only on its own key and inputs, so the scenes are those of a single call.

    The batch is split along the maps axis B when B >= workers (or S = 1), else along the
    samples axis S. The last part is padded with copies of the last map (or key), so every
    part has the same shape and one compilation serves all; the padding's scenes are dropped.

    Args:
      keys, params, maps, egos, given, caps: as in `sample_batch` (keys [B, S]).
      workers: concurrent calls (threads); default `concurrency.default_workers()` (one
        per core on CPU, 1 on accelerators).
      **kwargs: `sample_batch`'s static arguments (cfg, proposals, ..., parallel).

    Returns:
      Sample with leading axes [B, S].
    """
    workers = default_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    b, s = keys.shape[:2]
    axis = 0 if b >= workers or s == 1 else 1
    n = (b, s)[axis]
    size = -(-n // min(workers, n))
    parts = -(-n // size)
    if parts == 1:
        return sample_batch(keys, params, maps, egos, given, caps, **kwargs)
    index = np.minimum(np.arange(parts * size), n - 1).reshape(parts, size)
    per_map = (maps, egos, given, caps)

    def call(i):
        if axis == 0:
            return sample_batch(keys[i], params, *jax.tree.map(lambda x: x[i], per_map), **kwargs)
        return sample_batch(keys[:, i], params, *per_map, **kwargs)

    outs = list(concurrent_map(call, index, workers))
    whole = slice(None)
    keep = (slice(0, n), whole) if axis == 0 else (whole, slice(0, n))
    return jax.tree.map(lambda *x: jnp.concatenate(x, axis=axis)[keep], *outs)


def scene_keys(key: jax.Array, num_maps: int, num_per_map: int) -> jax.Array:
    """[B, S] keys of `sample_scenes`: split(key, B * S) reshaped."""
    return jax.random.split(key, num_maps * num_per_map).reshape(num_maps, num_per_map)


def batch_inputs(cfg: Config, num_maps: int, given: Actors | None = None, caps=None):
    """(given Actors [B, N], caps int32 [B, 3]) for `sample_batch` from optional inputs.

    `given` may be None, Actors [G] (shared by all maps) or Actors [B, G]; `caps` None, [3]
    or [B, 3].
    """
    n = cfg.max_actors
    if given is None:
        given = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_maps, *x.shape)), empty_actors(n))
    else:
        given = jax.tree.map(jnp.asarray, given)
        if given.cls.ndim == 1:
            given = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_maps, *x.shape)), given)
        given = jax.vmap(lambda g: _pad_given(g, n))(given)
    if caps is None:
        caps = jnp.full((num_maps, NUM_CLASSES), n, jnp.int32)
    caps = jnp.broadcast_to(jnp.asarray(caps, jnp.int32), (num_maps, NUM_CLASSES))
    return given, caps


def sample_scenes(
    key: jax.Array,
    params: Any,
    cfg: Config,
    maps: jnp.ndarray,
    egos: Actors,
    given: Actors | None = None,
    num_per_map: int = 1,
    caps=None,
    *,
    proposals: int | None = None,
    candidates: int = DEFAULT_CANDIDATES,
    rounds: int = DEFAULT_ROUNDS,
    heatmap_steps: tuple[int, ...] = (),
    model: Model | None = None,
    parallel: int | None = None,
    workers: int | None = None,
) -> Sample:
    """Samples `num_per_map` scenes for each of B maps (`sample_split`).

    Scene (b, s) is `rollout(scene_keys(key, B, S)[b, s], params, maps[b], egos[b], ...)`
    bit for bit, so the same key gives the same scenes.

    Args:
      key: PRNG key.
      params: network parameters.
      cfg: config.
      maps: float32 [B, H, W, Cm] map channels.
      egos: Actors [B].
      given: optional Actors [G] (shared) or [B, G] to condition on (see `rollout`).
      num_per_map: S, samples per map.
      caps: optional int32 [3] or [B, 3] per-class caps.
      proposals, candidates, rounds, heatmap_steps, model: see `rollout`.
      parallel: scenes vmapped together, see `sample_batch`.
      workers: concurrent calls, see `sample_split`.

    Returns:
      Sample with leading axes [B, S].
    """
    b = maps.shape[0]
    given, caps = batch_inputs(cfg, b, given, caps)
    return sample_split(scene_keys(key, b, num_per_map), params, maps, egos, given, caps,
                        workers=workers, cfg=cfg, proposals=proposals, candidates=candidates,
                        rounds=rounds, heatmap_steps=heatmap_steps, model=model,
                        parallel=parallel)
