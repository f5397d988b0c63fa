"""Autoregressive sampling of traffic scenes (paper sec. 3.3, SPEC sec. 6), jitted and vmapped.

`rollout` generates ONE scene (unbatched) inside a single traced function: a `lax.while_loop`
over the steps, at most `cfg.grid.max_actors`, the first from the zero ConvLSTM state, whose carry
(`SamplerState`) holds the ConvLSTM state, the actor raster, the actors so far, the previous
bin and a done flag. No host transfer, no Python loop over steps. The loop exits as soon as
the scene is done; under `vmap` it runs until every scene of the batch is done and finished
scenes are left unchanged (`lax.while_loop`'s batching rule selects their old carry), so a
batched call returns exactly the per-scene results. `sampling.batch` maps it over scenes and
keys; `sampling.attributes` draws each actor's box, heading and velocity.

One step t (key `fold_in(key, t)`):
  1. Input gates = map gates (computed once per scene before the loop: the map is constant)
     + actor gates of the current actor raster (carried, and updated after each step by a
     convolution over the new actor's drawing window only: `SceneGenNet.next_actor_gates`)
     + with `order_channel`, the gates of the bins at or after the previous actor's bin;
     ConvLSTM step; backbone features.
  2. Class from the categorical over (vehicle, pedestrian, bicyclist, stop); classes at their
     cap get zero mass. STOP ends the scene.
  3. Location: the class's logits masked to bins >= the previous actor's bin (canonical
     order, ties allowed) and renormalised; no allowed bin ends the scene.
  4. Candidates: R = `candidates` i.i.d. (bin, uniform position in the bin, attributes) draws.
     Attributes come from the class's MLP at the bin's feature vector (with
     `attribute_map_input`, and the map channels at the bin): heading and velocity are each
     the most likely of M = `proposals` draws (best-of-M; M = 1 is plain sampling), the box
     size is one draw (`sampling.attributes`). The bin is one draw too: the paper's
     supplementary 3.2 also takes the best of M positions, but with our models that puts
     each actor on the likeliest bins just after the previous one, and crowds the scenes
     into the first rows of road. Pedestrians:
     nominal square box (`cfg.grid.pedestrian_size_m`), heading = the velocity direction (0 when
     standing); their box and heading are not modelled.
  5. Collision rejection: a vehicle or bicyclist candidate whose box overlaps the ego or an
     earlier vehicle/bicyclist box is rejected; the first accepted candidate is kept. The first
     round of candidates is exact rejection sampling (the first acceptance in an i.i.d.
     sequence); when all R fail, their bins are masked out and another round is drawn, at
     most `rounds` rounds; if none is accepted (or no bin is left), the scene stops. So the
     output never holds overlapping vehicle/bicyclist boxes (`sampling.placement`).
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
import enum
import functools
import numbers
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import masked_log_softmax, ordering_mask, sample_class
from scenegen_jax.raster.actors import draw_actor, empty_actor_raster
from scenegen_jax.sampling.model import Model, NetworkModel
from scenegen_jax.sampling.placement import place_actor
from scenegen_jax.scene import (
    NUM_CLASSES,
    STOP,
    Actors,
    bin_index,
    canonical_order,
    empty_actors,
    tree_take,
)

DEFAULT_CANDIDATES = 8
DEFAULT_ROUNDS = 4
# The steps whose location distributions the paper's Figure 7 shows.
HEATMAP_STEPS = (0, 5, 10, 15, 20)
# The least location temperature: at 1e-3 a logit gap of 0.01 already weighs e^10 : 1, so
# the draw is the likeliest allowed bin; far below it the logits divided by the temperature
# leave float32's range (1e-300 is 0 in float32: every bin NaN, every scene empty).
MIN_LOCATION_TEMPERATURE = 1e-3


@dataclasses.dataclass(frozen=True)
class SamplerOptions:
    """The sampler's settings (hashable: one compilation per distinct value, but for the
    temperature, which `sample_batch` passes as an array: every temperature runs one program).

    proposals: M of best-of-M; None: the config's `sample.proposals` (`sampling.batch.sample_scenes`
      sets it; `rollout` needs it set).
    candidates: R, candidate draws per collision-rejection round.
    rounds: rejection rounds before a scene stops.
    heatmap_steps: steps whose location distribution is recorded.
    parallel: scenes vmapped together by `sample_batch`; None: `backend.default_parallel()`
      (1 on CPU, all on accelerators).
    location_temperature: the location logits are divided by it before the ordering mask
      and the softmax (beyond the paper, whose sampler is 1.0, the default): below 1 the
      draw favours the model's likelier bins.
    """

    proposals: int | None = None
    candidates: int = DEFAULT_CANDIDATES
    rounds: int = DEFAULT_ROUNDS
    heatmap_steps: tuple[int, ...] = ()
    parallel: int | None = None
    location_temperature: float = 1.0

    def __post_init__(self):
        # numpy scalars are taken as the Python numbers they hold (a hashable, static option).
        for name in ("proposals", "candidates", "rounds", "parallel"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, numbers.Integral)
                                  or v < 1):
                raise ValueError(f"sampler option {name} must be an integer >= 1, got {v!r}")
            object.__setattr__(self, name, None if v is None else int(v))
        t = self.location_temperature
        if (isinstance(t, bool) or not isinstance(t, numbers.Real)
                or not MIN_LOCATION_TEMPERATURE <= t < float("inf")):
            raise ValueError(f"sampler option location_temperature must be a number >= "
                             f"{MIN_LOCATION_TEMPERATURE:g} (below it the draw is already the "
                             f"likeliest bin, and the divided logits leave float32's range), "
                             f"got {t!r}")
        object.__setattr__(self, "location_temperature", float(t))
        steps = self.heatmap_steps
        steps = steps if isinstance(steps, numbers.Number) else tuple(steps)  # a generator once
        if isinstance(steps, numbers.Number) or not all(
                isinstance(k, numbers.Integral) and not isinstance(k, bool) and k >= 0
                for k in steps):
            raise ValueError(f"sampler option heatmap_steps must be integers >= 0, got {steps!r}")
        object.__setattr__(self, "heatmap_steps", tuple(int(k) for k in steps))


DEFAULT_OPTIONS = SamplerOptions()

class StopReason(enum.IntEnum):
    """Why a sampled scene ended (`Sample.stop_reason`; not the stop token's class id,
    `scene.STOP`)."""

    STOP_TOKEN = 0  # the model drew the stop token
    FULL = 1  # every actor slot is filled
    NO_BIN = 2  # the ordering mask and the location logits left no bin
    COLLISION = 3  # every candidate of every round overlapped an earlier actor


# Their names in sampled scenes' records, indexed by `StopReason`: "stop_token", ...
STOP_REASONS = tuple(reason.name.lower() for reason in StopReason)


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
      stop_reason: int32 [] a `StopReason` (valid when done).
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


def pad_given(given: Actors | None, n: int) -> Actors:
    """Given actors padded (or created empty) to n slots; raises if more than n slots."""
    if given is None:
        return jax.tree.map(jnp.asarray, empty_actors(n))
    slots = given.cls.shape[0]
    if slots > n:
        raise ValueError(f"given actors: {slots} slots, more than max_actors = {n}")
    return jax.tree.map(
        lambda x: jnp.pad(jnp.asarray(x), [(0, n - slots)] + [(0, 0)] * (jnp.ndim(x) - 1)), given
    )



class _Inputs(NamedTuple):
    """What every step of one scene's rollout reads: the key, the model's parameters, the map
    [1, H, W, Cm] and its share of layer 1's gates, the ego, the given actors [N] (canonical,
    padded) and their count, the class caps [3], the steps whose location distributions are
    recorded and the location temperature."""

    key: jax.Array
    params: Any
    map_raster: jnp.ndarray
    map_gates: jnp.ndarray
    ego: Actors
    given: Actors
    n_given: jnp.ndarray
    caps: jnp.ndarray
    heatmap_steps: jnp.ndarray
    location_temperature: Any


def _step_class(model: Model, inputs: _Inputs, state: SamplerState, f, key, n: int):
    """Step 2: (class, whether the step is teacher forced, the given actor of the step): the
    given actor's class while given actors last, else a draw from the class logits of the
    features f with the classes at their cap masked out."""
    t = state.count
    logits = model.class_logits(inputs.params, f)[0]
    full_class = state.class_counts >= inputs.caps
    logits = logits.at[:NUM_CLASSES].set(jnp.where(full_class, -jnp.inf, logits[:NUM_CLASSES]))
    forced = t < inputs.n_given
    g = tree_take(inputs.given, jnp.minimum(t, n - 1))
    cls = jnp.where(forced, g.cls, sample_class(key, logits)).astype(jnp.int32)
    return cls, forced, g


def _step_log_probs(model: Model, inputs: _Inputs, state: SamplerState, f, cls, n_bins: int):
    """Step 3: the location log-probabilities [H*W] of class `cls` (the temperature's logits
    masked to the bins the canonical order allows, renormalised; -inf elsewhere)."""
    loc = model.location_logits(inputs.params, f, cls[None])[0]
    loc = loc / inputs.location_temperature
    log_probs, _ = masked_log_softmax(loc, ordering_mask(state.prev_bin, n_bins))
    # Bins allowed by the mask but with -inf logits give NaN in the softmax; drop them.
    return jnp.where(jnp.isnan(log_probs), -jnp.inf, log_probs)


def _step(model: Model, cfg: ModelConfig, options: SamplerOptions, proposals: int, inputs: _Inputs,
          state: SamplerState) -> SamplerState:
    """One step of the rollout (the module docstring's steps 1 to 6)."""
    n, n_bins, params = cfg.grid.max_actors, cfg.grid.grid_size * cfg.grid.grid_size, inputs.params
    t = state.count
    k_class, k_place = jax.random.split(jax.random.fold_in(inputs.key, t))
    gates = (inputs.map_gates + state.actor_gates
             + model.order_gates(params, state.prev_bin[None]))
    lstm, h = model.recur(params, state.lstm, gates)
    f = model.features(params, h)
    cls, forced, g = _step_class(model, inputs, state, f, k_class, n)
    is_stop = cls == STOP
    safe_cls = jnp.where(is_stop, 0, cls)
    log_probs = _step_log_probs(model, inputs, state, f, safe_cls, n_bins)
    any_valid = jnp.any(jnp.isfinite(log_probs))
    # Forced and stop steps draw no candidates (no allowed bin: the round loop is skipped).
    place_lp = jnp.where(forced | is_stop, -jnp.inf, log_probs)
    sampled, found, rejected = place_actor(k_place, params, model, f, inputs.map_raster,
                                           safe_cls, place_lp, state.actors, inputs.ego, cfg,
                                           proposals, options.candidates, options.rounds)
    actor = _where(forced, g.replace(valid=jnp.bool_(True)), sampled)
    placed = forced | (jnp.logical_not(is_stop) & any_valid & found)
    actor = actor.replace(valid=placed)

    actors = jax.tree.map(lambda a, x: a.at[t].set(x), state.actors, actor)
    count = t + placed.astype(jnp.int32)
    done = jnp.logical_not(placed) | (count >= n)
    reason = jnp.select(
        [placed, is_stop, jnp.logical_not(any_valid)],
        [StopReason.FULL, StopReason.STOP_TOKEN, StopReason.NO_BIN], StopReason.COLLISION
    ).astype(jnp.int32)
    hit = inputs.heatmap_steps == t
    probs = jnp.where(is_stop, 0.0, jnp.exp(log_probs))
    raster = draw_actor(state.raster, actor, False, cfg.grid)
    return SamplerState(
        lstm=lstm,
        raster=raster,
        actor_gates=model.next_actor_gates(params, state.actor_gates, state.raster[None],
                                           raster[None], actor.position[None]),
        actors=actors,
        count=count,
        prev_bin=jnp.where(placed, bin_index(actor.position, cfg.grid), state.prev_bin),
        done=done,
        class_counts=state.class_counts + (jnp.arange(NUM_CLASSES) == cls) * placed,
        stop_reason=jnp.where(done, reason, state.stop_reason),
        rejected=state.rejected + rejected,
        heatmaps=jnp.where(hit[:, None], probs[None], state.heatmaps),
        heatmap_cls=jnp.where(hit, cls, state.heatmap_cls),
    )


def _initial_state(model: Model, params, raster, n: int, heatmaps: int,
                   n_bins: int) -> SamplerState:
    """The loop's first carry: the zero ConvLSTM state, the ego-only raster and its actor
    gates, no actors, `heatmaps` location distributions of `n_bins` bins to record."""
    return SamplerState(
        lstm=model.initial_state(params),
        raster=raster,
        actor_gates=model.actor_gates(params, raster[None]),
        actors=jax.tree.map(jnp.asarray, empty_actors(n)),
        count=jnp.int32(0),
        prev_bin=jnp.int32(0),
        done=jnp.bool_(n == 0),
        class_counts=jnp.zeros((NUM_CLASSES,), jnp.int32),
        stop_reason=jnp.int32(StopReason.FULL),
        rejected=jnp.int32(0),
        heatmaps=jnp.zeros((heatmaps, n_bins), jnp.float32),
        heatmap_cls=jnp.full((heatmaps,), -1, jnp.int32),
    )


def rollout(
    key: jax.Array,
    params: Any,
    map_raster: jnp.ndarray,
    ego: Actors,
    cfg: ModelConfig,
    given: Actors | None = None,
    caps: jnp.ndarray | None = None,
    options: SamplerOptions = DEFAULT_OPTIONS,
    model: Model | None = None,
    location_temperature: jnp.ndarray | None = None,
) -> Sample:
    """Samples one scene (unbatched; jit and vmap outside, see `sample_batch`).

    Args:
      key: PRNG key; step t uses fold_in(key, t), so a key reproduces the scene bit for bit.
      params: network parameters (or whatever `model` takes).
      map_raster: float32 [H, W, Cm] map channels, already cropped to the grid.
      ego: the ego (Actors without a leading axis).
      cfg: the model config (its grid: max_actors N, zero_speed, pedestrian_size_m).
      given: optional Actors [G <= N] to condition on, inside the region with valid values
        (validate on the host, e.g. `Scene.validate` or `export.actors_from_records`); they
        are put in canonical order (a no-op when they already are).
      caps: optional int32 [3] maximum actors per class (given ones count); default N.
      options: static settings (`SamplerOptions`; its `parallel` is `sample_batch`'s).
      model: the network interface; default `NetworkModel(cfg)`.
      location_temperature: optional float32 [] in place of `options.location_temperature`,
        so that a traced value serves every temperature with one compiled program.

    Returns:
      Sample.
    """
    model = NetworkModel(cfg) if model is None else model
    if location_temperature is None:
        location_temperature = options.location_temperature
    if options.proposals is None:
        raise ValueError("options.proposals: None; `sampling.batch.sample_scenes` sets it from "
                         "the config's sample.proposals")
    m = options.proposals
    n = cfg.grid.max_actors
    # Stable sort: canonical input is unchanged, anything else is put in canonical order.
    given = canonical_order(pad_given(given, n), cfg.grid)
    n_given = jnp.sum(given.valid).astype(jnp.int32)
    caps = jnp.full((NUM_CLASSES,), n, jnp.int32) if caps is None else jnp.asarray(caps, jnp.int32)
    steps = jnp.asarray(options.heatmap_steps, jnp.int32).reshape(-1)
    ego = jax.tree.map(jnp.asarray, ego)

    map_raster = jnp.asarray(map_raster, jnp.float32)[None]
    map_gates = model.map_gates(params, map_raster)
    raster = draw_actor(empty_actor_raster(cfg.grid), ego, True, cfg.grid)
    inputs = _Inputs(key, params, map_raster, map_gates, ego, given, n_given, caps, steps,
                     location_temperature)
    init = _initial_state(model, params, raster, n, steps.shape[0],
                          cfg.grid.grid_size * cfg.grid.grid_size)
    # Every step in the loop, the first from the zero state with its (zero) recurrent
    # convolutions: a first step of its own would skip them but compile the step twice.
    step = functools.partial(_step, model, cfg, options, m, inputs)
    final = lax.while_loop(lambda s: jnp.logical_not(s.done), step, init)
    return Sample(
        actors=final.actors,
        num_given=jnp.minimum(n_given, final.count),
        stop_reason=final.stop_reason,
        rejected=final.rejected,
        heatmaps=final.heatmaps,
        heatmap_cls=final.heatmap_cls,
    )
