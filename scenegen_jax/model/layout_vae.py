"""LayoutVAE (Jyothi et al. 2019) adapted to traffic scenes as the paper's supplementary 2.1
describes: the learned baseline with a likelihood.

- A map CNN's pooled features (with the ego's velocity) replace the label-set encoding.
- CountVAE: for each class in turn (vehicles, pedestrians, bicyclists) a latent z with a
  conditional prior, and a Poisson count given z, the map and the counts so far.
- BBoxVAE: for each actor in turn (by class, then nearest the ego first) a latent z with a
  conditional prior given the map, the counts, the actor's class and an LSTM over the actors
  before it; given z, a bivariate Gaussian location (m), a bivariate log-normal box (width,
  length; m), a von Mises heading and a bivariate Gaussian velocity (m/s): the paper's
  outputs, with the heading that an oriented box needs. As in SceneGen, a pedestrian has no
  box nor heading term, nor has a box its size source did not measure, and a speed at or
  below the grid's `zero_speed` is a point mass: the velocity's measure is a probability of
  standing plus the Gaussian's density times that of moving (the Gaussian's little mass
  inside the `zero_speed` disc is not given back: the likelihood errs low, never high), so
  the NLLs of the two models are in the same units.

Training maximises the ELBO (one reparameterised sample per step). A scene's likelihood is
estimated by Monte Carlo with samples of the conditional prior (`log_likelihood`, 1,000 by
default): each step's term log E_z p(x_t | z, x_<t) from its own samples, whose sum is an
estimate of log p(x) because the steps' latents are independent given the scene.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.config import GridConfig
from scenegen_jax.distributions.mixtures import (
    VONMISES_UNIFORMS,
    vonmises_from_uniforms,
    vonmises_log_prob,
)
from scenegen_jax.scene import BICYCLIST, NUM_CLASSES, PEDESTRIAN, VEHICLE, Actors, in_region

ATTRIBUTE_SIZE = NUM_CLASSES + 8  # class one-hot, position, log size, heading, velocity
OUTPUT_SIZE = 19  # location 5, log box 5, heading 3, velocity 5, standing 1
VELOCITY_SCALE = 10.0  # m/s: velocities are read and written in these units
CLASS_ORDER = (VEHICLE, PEDESTRIAN, BICYCLIST)
LOG_2PI = float(np.log(2 * np.pi))


@dataclasses.dataclass(frozen=True)
class LayoutVAEConfig:
    """grid: the SceneGen config's grid it generates on; latent: z's size per step; hidden:
    the MLPs' and the LSTM's width; widths: the map CNN's three stages."""

    grid: GridConfig
    latent: int = 16
    hidden: int = 128
    widths: tuple[int, int, int] = (32, 64, 64)

    @property
    def max_actors(self) -> int:
        return self.grid.max_actors

    def to_dict(self) -> dict:
        return {"latent": self.latent, "hidden": self.hidden, "widths": list(self.widths)}

    @classmethod
    def from_dict(cls, d: dict, grid: GridConfig) -> LayoutVAEConfig:
        return cls(grid=grid, latent=int(d["latent"]), hidden=int(d["hidden"]),
                   widths=tuple(d["widths"]))


# ---------------------------------------------------------------------------- scenes


def layout_order(actors: Actors, grid: GridConfig) -> tuple[np.ndarray, np.ndarray]:
    """(slot order [A], kept [A]) of one scene's numpy actors: the valid ones inside the
    region by class (CLASS_ORDER), then nearest the ego first; at most grid.max_actors."""
    keep = np.asarray(actors.valid) & np.asarray(in_region(np.asarray(actors.position), grid))
    rank = np.array([CLASS_ORDER.index(int(c)) for c in np.asarray(actors.cls)])
    dist = np.linalg.norm(np.asarray(actors.position, np.float64), axis=-1)
    order = np.lexsort((dist, rank, ~keep))
    kept = keep[order]
    kept[grid.max_actors:] = False
    return order[: grid.max_actors], kept[: grid.max_actors]


def layout_arrays(actors: Actors, grid: GridConfig) -> dict:
    """One scene as LayoutVAE reads it: counts [3] (CLASS_ORDER), and per step [L]: cls,
    position [L, 2], size [L, 2], heading, velocity [L, 2], valid, measured (L =
    grid.max_actors; padding steps invalid)."""
    order, kept = layout_order(actors, grid)
    n = grid.max_actors
    pad = n - len(order)

    def take(x, fill=0):
        x = np.asarray(x)[order]
        return np.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1), constant_values=fill)

    valid = np.pad(kept, (0, pad))
    cls = np.where(valid, take(actors.cls), 0).astype(np.int32)
    return {
        "counts": np.array([np.sum(valid & (cls == c)) for c in CLASS_ORDER], np.int32),
        "cls": cls,
        "position": take(actors.position).astype(np.float32),
        "size": take(actors.size, 1.0).astype(np.float32),
        "heading": take(actors.heading).astype(np.float32),
        "velocity": take(actors.velocity).astype(np.float32),
        "valid": valid,
        "measured": np.pad(np.asarray(actors.size_measured)[order] & kept, (0, pad)),
    }


def attribute_features(cls, position, size, heading, velocity, grid: GridConfig):
    """[..., ATTRIBUTE_SIZE] the actors' attributes as the networks read them."""
    ped = cls == PEDESTRIAN
    log_size = jnp.where(ped[..., None], 0.0, jnp.log(jnp.maximum(size, 1e-3)))
    cos_sin = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1) * (~ped[..., None])
    return jnp.concatenate([jax.nn.one_hot(cls, NUM_CLASSES), position / (grid.region_m / 2),
                            log_size, cos_sin, velocity / VELOCITY_SCALE], -1)


# ---------------------------------------------------------------------------- densities


def gaussian2_log_prob(x, raw):
    """log density of x [..., 2] under a bivariate Gaussian of raw [..., 5]: mean, log
    standard deviations and the correlation's atanh (tanh-bounded to +-0.95)."""
    mean, log_std, rho = raw[..., :2], raw[..., 2:4], 0.95 * jnp.tanh(raw[..., 4])
    z = (x - mean) * jnp.exp(-log_std)
    q = (z[..., 0] ** 2 - 2 * rho * z[..., 0] * z[..., 1] + z[..., 1] ** 2) / (1 - rho**2)
    return -LOG_2PI - log_std.sum(-1) - 0.5 * jnp.log1p(-(rho**2)) - 0.5 * q


def gaussian2_sample(key, raw):
    mean, std, rho = raw[..., :2], jnp.exp(raw[..., 2:4]), 0.95 * jnp.tanh(raw[..., 4])
    e = jax.random.normal(key, mean.shape)
    z1 = e[..., 0]
    z2 = rho * e[..., 0] + jnp.sqrt(1 - rho**2) * e[..., 1]
    return mean + std * jnp.stack([z1, z2], -1)


def poisson_log_prob(k, log_rate):
    k = k.astype(jnp.float32)
    return k * log_rate - jnp.exp(log_rate) - jax.scipy.special.gammaln(k + 1)


def gaussian_kl(mu_q, logvar_q, mu_p, logvar_p):
    """KL(q || p) [...] of diagonal Gaussians [..., Z]."""
    return 0.5 * jnp.sum(logvar_p - logvar_q + (jnp.exp(logvar_q) + (mu_q - mu_p) ** 2)
                         * jnp.exp(-logvar_p) - 1.0, -1)


def actor_log_prob(out, cls, position, size, heading, velocity, measured, grid: GridConfig):
    """log p [...] of actors' attributes under decoder outputs `out` [..., OUTPUT_SIZE]:
    location (m^-2), box (m^-2, only for a measured vehicle or bicyclist box), heading
    (rad^-1, not for pedestrians), velocity (the probability of standing, or that of moving
    times the density in (m/s)^-2)."""
    scale = grid.region_m / 2
    loc = gaussian2_log_prob(position / scale, out[..., 0:5]) - 2 * np.log(scale)
    boxed = (cls != PEDESTRIAN) & measured
    log_size = jnp.log(jnp.maximum(size, 1e-3))
    box = gaussian2_log_prob(log_size, out[..., 5:10]) - log_size.sum(-1)
    head = vonmises_log_prob(heading, out[..., 10:12], out[..., 12])
    moving = (gaussian2_log_prob(velocity / VELOCITY_SCALE, out[..., 13:18])
              - 2 * np.log(VELOCITY_SCALE))
    standing = jnp.sum(velocity**2, -1) <= grid.zero_speed**2
    vel = jnp.where(standing, jax.nn.log_sigmoid(out[..., 18]),
                    jax.nn.log_sigmoid(-out[..., 18]) + moving)
    return loc + jnp.where(boxed, box, 0.0) + jnp.where(cls != PEDESTRIAN, head, 0.0) + vel


def sample_actor(key, out, cls, grid: GridConfig):
    """(position [..., 2], size [..., 2], heading, velocity [..., 2]) drawn from `out`."""
    k = jax.random.split(key, 5)
    scale = grid.region_m / 2
    position = gaussian2_sample(k[0], out[..., 0:5]) * scale
    size = jnp.exp(gaussian2_sample(k[1], out[..., 5:10]))
    lead = out.shape[:-1]
    u = jax.random.uniform(k[2], (int(np.prod(lead)), VONMISES_UNIFORMS))
    heading = jax.vmap(vonmises_from_uniforms)(
        u, out[..., 10:12].reshape(-1, 2), out[..., 12].reshape(-1)).reshape(lead)
    velocity = gaussian2_sample(k[3], out[..., 13:18]) * VELOCITY_SCALE
    standing = jax.random.uniform(k[4], out.shape[:-1]) < jax.nn.sigmoid(out[..., 18])
    velocity = jnp.where(standing[..., None], 0.0, velocity)
    ped = cls == PEDESTRIAN
    size = jnp.where(ped[..., None], grid.pedestrian_size_m, size)
    heading = jnp.where(ped, 0.0, heading)
    return position, size, heading, velocity


# ---------------------------------------------------------------------------- networks


class _MLP(nn.Module):
    hidden: int
    out: int

    @nn.compact
    def __call__(self, x):
        x = nn.relu(nn.Dense(self.hidden)(x))
        x = nn.relu(nn.Dense(self.hidden)(x))
        return nn.Dense(self.out)(x)


class LayoutVAE(nn.Module):
    cfg: LayoutVAEConfig

    def setup(self):
        c = self.cfg
        self.convs = [nn.Conv(w, (3, 3), strides=(s, s)) for w, s in
                      ((c.widths[0], 1), (c.widths[1], 2), (c.widths[2], 2))]
        self.norms = [nn.GroupNorm(num_groups=8) for _ in c.widths]
        self.count_prior = _MLP(c.hidden, 2 * c.latent)
        self.count_encoder = _MLP(c.hidden, 2 * c.latent)
        self.count_decoder = _MLP(c.hidden, 1)
        self.box_prior = _MLP(c.hidden, 2 * c.latent)
        self.box_encoder = _MLP(c.hidden, 2 * c.latent)
        self.box_decoder = _MLP(c.hidden, OUTPUT_SIZE)
        self.lstm = nn.OptimizedLSTMCell(c.hidden)

    def condition(self, maps, ego_velocity):
        """[B, F] the scene's condition: the pooled map features (multi-scale) and the ego's
        velocity."""
        x, pooled = maps, []
        for conv, norm in zip(self.convs, self.norms, strict=True):
            x = nn.relu(norm(conv(x)))
            pooled.append(x.mean(axis=(1, 2)))
        return jnp.concatenate([*pooled, ego_velocity / VELOCITY_SCALE], -1)

    def count_inputs(self, cond, counts):
        """[B, 3, F'] the inputs of the three count steps: the condition, the class and the
        counts of the classes before it."""
        b = cond.shape[0]
        before = jnp.log1p(counts.astype(jnp.float32))[:, None, :] * jnp.tril(
            jnp.ones((NUM_CLASSES, NUM_CLASSES)), -1)[None]
        onehot = jnp.broadcast_to(jnp.eye(NUM_CLASSES), (b, NUM_CLASSES, NUM_CLASSES))
        return jnp.concatenate([jnp.broadcast_to(cond[:, None], (b, NUM_CLASSES,
                                                                 cond.shape[-1])),
                                onehot, before], -1)

    def box_inputs(self, cond, counts, cls, features):
        """[B, L, F'] the inputs of the actor steps: the condition, the counts, the actor's
        class and the LSTM's state after the actors before it (`features` [B, L, ATTR])."""
        b, n = cls.shape
        carry = self.lstm.initialize_carry(jax.random.key(0), (b, ATTRIBUTE_SIZE))

        def step(cell, carry, x):
            carry, h = cell(carry, x)
            return carry, h

        scan = nn.scan(step, variable_broadcast="params", split_rngs={"params": False},
                       in_axes=1, out_axes=1)
        shifted = jnp.concatenate([jnp.zeros_like(features[:, :1]), features[:, :-1]], 1)
        _, states = scan(self.lstm, carry, shifted)
        return self._box_inputs(cond, counts, cls, states)

    def _box_inputs(self, cond, counts, cls, states):
        lead = cls.shape
        return jnp.concatenate([
            jnp.broadcast_to(cond[:, None], (*lead, cond.shape[-1])),
            jnp.broadcast_to(jnp.log1p(counts.astype(jnp.float32))[:, None],
                             (*lead, NUM_CLASSES)),
            jax.nn.one_hot(cls, NUM_CLASSES), states], -1)

    def lstm_step(self, carry, x):
        return self.lstm(carry, x)

    def __call__(self, maps, ego_velocity, counts, cls, features):
        """Everything `elbo` reads (init traces every submodule)."""
        cond = self.condition(maps, ego_velocity)
        ci = self.count_inputs(cond, counts)
        bi = self.box_inputs(cond, counts, cls, features)
        logc = jnp.log1p(counts.astype(jnp.float32))[..., None]
        z_c = jnp.zeros((*ci.shape[:-1], self.cfg.latent))
        z_b = jnp.zeros((*bi.shape[:-1], self.cfg.latent))
        return (self.count_prior(ci), self.count_encoder(jnp.concatenate([ci, logc], -1)),
                self.count_decoder(jnp.concatenate([ci, z_c], -1)), self.box_prior(bi),
                self.box_encoder(jnp.concatenate([bi, features], -1)),
                self.box_decoder(jnp.concatenate([bi, z_b], -1)))


def init_layout_vae(cfg: LayoutVAEConfig, seed: int = 0):
    g, n = cfg.grid.grid_size, cfg.max_actors
    maps = jnp.zeros((1, g, g, len(cfg.grid.map_channels)))
    return LayoutVAE(cfg).init(
        jax.random.key(seed), maps, jnp.zeros((1, 2)), jnp.zeros((1, NUM_CLASSES), jnp.int32),
        jnp.zeros((1, n), jnp.int32), jnp.zeros((1, n, ATTRIBUTE_SIZE)))["params"]


def _call(params, cfg: LayoutVAEConfig, method, *args):
    return LayoutVAE(cfg).apply({"params": params}, *args, method=method)


def _halves(x):
    return jnp.split(x, 2, axis=-1)


# ---------------------------------------------------------------------------- likelihood


def _steps(params, cfg: LayoutVAEConfig, batch: dict):
    """(count inputs [B, 3, F], actor inputs [B, L, F], actor features [B, L, ATTR])."""
    m = LayoutVAE
    cond = _call(params, cfg, m.condition, batch["maps"], batch["ego_velocity"])
    feats = attribute_features(batch["cls"], batch["position"], batch["size"], batch["heading"],
                               batch["velocity"], cfg.grid)
    ci = _call(params, cfg, m.count_inputs, cond, batch["counts"])
    bi = _call(params, cfg, m.box_inputs, cond, batch["counts"], batch["cls"], feats)
    return ci, bi, feats


def _count_log_prob(params, cfg, ci, z, counts):
    log_rate = _call(params, cfg, lambda s, x: s.count_decoder(x),
                     jnp.concatenate([ci, z], -1))[..., 0]
    return poisson_log_prob(counts, jnp.clip(log_rate, -10.0, 6.0))


def _box_log_prob(params, cfg, bi, z, batch, lead=()):
    out = _call(params, cfg, lambda s, x: s.box_decoder(x), jnp.concatenate([bi, z], -1))
    expand = (lambda x: x[(slice(None),) * 2 + (None,) * len(lead)]) if lead else (lambda x: x)
    return actor_log_prob(out, expand(batch["cls"]), expand(batch["position"]),
                          expand(batch["size"]), expand(batch["heading"]),
                          expand(batch["velocity"]), expand(batch["measured"]), cfg.grid)


def elbo_loss(params, batch: dict, key, cfg: LayoutVAEConfig):
    """The negative ELBO per scene, averaged over the batch (one reparameterised z per
    step)."""
    ci, bi, feats = _steps(params, cfg, batch)
    k1, k2 = jax.random.split(key)
    logc = jnp.log1p(batch["counts"].astype(jnp.float32))[..., None]
    mu_p, lv_p = _halves(_call(params, cfg, lambda s, x: s.count_prior(x), ci))
    mu_q, lv_q = _halves(_call(params, cfg, lambda s, x: s.count_encoder(x),
                               jnp.concatenate([ci, logc], -1)))
    z = mu_q + jnp.exp(0.5 * lv_q) * jax.random.normal(k1, mu_q.shape)
    counts = _count_log_prob(params, cfg, ci, z, batch["counts"]) - gaussian_kl(
        mu_q, lv_q, mu_p, lv_p)
    mu_p, lv_p = _halves(_call(params, cfg, lambda s, x: s.box_prior(x), bi))
    mu_q, lv_q = _halves(_call(params, cfg, lambda s, x: s.box_encoder(x),
                               jnp.concatenate([bi, feats], -1)))
    z = mu_q + jnp.exp(0.5 * lv_q) * jax.random.normal(k2, mu_q.shape)
    boxes = _box_log_prob(params, cfg, bi, z, batch) - gaussian_kl(mu_q, lv_q, mu_p, lv_p)
    boxes = jnp.where(batch["valid"], boxes, 0.0)
    return -(counts.sum(-1) + boxes.sum(-1)).mean()


def prior_params(params, cfg: LayoutVAEConfig, batch: dict):
    """The conditional priors' (mean, log variance) of every step: counts ([B, 3, Z] each)
    and actors ([B, L, Z] each), given the scene's earlier steps."""
    ci, bi, _ = _steps(params, cfg, batch)
    return (_halves(_call(params, cfg, lambda s, x: s.count_prior(x), ci)),
            _halves(_call(params, cfg, lambda s, x: s.box_prior(x), bi)))


def step_log_probs(params, cfg: LayoutVAEConfig, batch: dict, z_counts, z_actors):
    """log p(x_t | z, x_<t) of every step at K latents each: counts [B, 3, K] given z_counts
    [B, 3, K, Z], actors [B, L, K] given z_actors [B, L, K, Z]."""
    ci, bi, _ = _steps(params, cfg, batch)

    def expand(x, z):
        return jnp.broadcast_to(x[..., None, :], (*z.shape[:-1], x.shape[-1]))

    counts = _count_log_prob(params, cfg, expand(ci, z_counts), z_counts,
                             batch["counts"][..., None])
    actors = _box_log_prob(params, cfg, expand(bi, z_actors), z_actors, batch,
                           lead=(z_actors.shape[-2],))
    return counts, actors


def step_log_likelihoods(params, cfg: LayoutVAEConfig, batch: dict, key, samples: int = 1000):
    """Monte-Carlo log p of each step: (counts [B, 3], actors [B, L], 0 where invalid), each
    log mean_k p(x_t | z_k, x_<t) over `samples` draws z_k of its conditional prior."""
    (mu_c, lv_c), (mu_a, lv_a) = prior_params(params, cfg, batch)
    k1, k2 = jax.random.split(key)

    def draws(key, mu, lv):
        e = jax.random.normal(key, (*mu.shape[:-1], samples, mu.shape[-1]))
        return mu[..., None, :] + jnp.exp(0.5 * lv)[..., None, :] * e

    lp_c, lp_a = step_log_probs(params, cfg, batch, draws(k1, mu_c, lv_c),
                                draws(k2, mu_a, lv_a))
    counts = jax.nn.logsumexp(lp_c, -1) - np.log(samples)
    actors = jnp.where(batch["valid"], jax.nn.logsumexp(lp_a, -1) - np.log(samples), 0.0)
    return counts, actors


# ---------------------------------------------------------------------------- sampling


def sample_layouts(params, cfg: LayoutVAEConfig, maps, ego_velocity, key):
    """Scenes [B] drawn from the model: Actors [B, L] (at most L = grid.max_actors; actors
    drawn outside the region are dropped, as a scene holds only the region's actors)."""
    m = LayoutVAE
    b, n = maps.shape[0], cfg.max_actors
    cond = _call(params, cfg, m.condition, maps, ego_velocity)
    keys = jax.random.split(key, NUM_CLASSES + 1)
    counts = jnp.zeros((b, NUM_CLASSES), jnp.int32)
    for c in range(NUM_CLASSES):  # each class's count given the ones before
        ci = _call(params, cfg, m.count_inputs, cond, counts)[:, c]
        mu, lv = _halves(_call(params, cfg, lambda s, x: s.count_prior(x), ci))
        kz, kp = jax.random.split(keys[c])
        z = mu + jnp.exp(0.5 * lv) * jax.random.normal(kz, mu.shape)
        log_rate = _call(params, cfg, lambda s, x: s.count_decoder(x),
                         jnp.concatenate([ci, z], -1))[..., 0]
        drawn = jax.random.poisson(kp, jnp.exp(jnp.clip(log_rate, -10.0, 6.0)))
        counts = counts.at[:, c].set(jnp.minimum(drawn, n).astype(jnp.int32))
    ends = jnp.cumsum(counts, -1)
    steps = jnp.arange(n)
    rank = jnp.sum(steps[None, :, None] >= ends[:, None, :], -1)  # [B, L] class rank
    valid = steps[None] < ends[:, -1:]
    cls = jnp.asarray(CLASS_ORDER)[jnp.minimum(rank, NUM_CLASSES - 1)]
    counts = jnp.diff(jnp.minimum(ends, n), prepend=0, axis=-1)  # what fits in L steps

    def step(carry, inputs):
        lstm_carry, prev = carry
        c, k = inputs
        lstm_carry, h = _call(params, cfg, m.lstm_step, lstm_carry, prev)
        bi = _call(params, cfg, m._box_inputs, cond, counts, c[:, None], h[:, None])[:, 0]
        mu, lv = _halves(_call(params, cfg, lambda s, x: s.box_prior(x), bi))
        kz, ka = jax.random.split(k)
        z = mu + jnp.exp(0.5 * lv) * jax.random.normal(kz, mu.shape)
        out = _call(params, cfg, lambda s, x: s.box_decoder(x), jnp.concatenate([bi, z], -1))
        pos, size, heading, vel = sample_actor(ka, out, c, cfg.grid)
        feats = attribute_features(c, pos, size, heading, vel, cfg.grid)
        return (lstm_carry, feats), (pos, size, heading, vel)

    carry = (tuple(jnp.zeros((b, cfg.hidden)) for _ in range(2)),
             jnp.zeros((b, ATTRIBUTE_SIZE)))
    _, (pos, size, heading, vel) = jax.lax.scan(
        step, carry, (cls.T, jax.random.split(keys[-1], n)))
    pos, size, vel = (jnp.swapaxes(x, 0, 1) for x in (pos, size, vel))
    heading = heading.T
    valid = valid & in_region(pos, cfg.grid)
    return Actors(cls=jnp.where(valid, cls, 0).astype(jnp.int32), position=pos, size=size,
                  heading=jnp.mod(heading, 2 * np.pi), velocity=vel, valid=valid,
                  size_measured=valid)
