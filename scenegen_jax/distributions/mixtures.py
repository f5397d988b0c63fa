"""Mixture densities and samplers of the actor attributes: box size, heading, velocity.

All functions are per example (one actor, unbatched) and take the raw head output (see
`params` for the layouts); vmap them for batches. Mixture log-densities are a logsumexp over
`log_softmax(logits) + component log-density`, as in distrax's MixtureSameFamily.
Samplers take the key first and never return NaN: samples are clamped to
`SAMPLE_LOG_RANGE` in log space (a finiteness guard far outside any real box or speed).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy import special

from scenegen_jax.distributions import params as P
from scenegen_jax.distributions.categorical import gumbel_argmax, uniforms
from scenegen_jax.scene import tree_take, wrap_angle

LOG_2PI = math.log(2.0 * math.pi)
# Samples of log width, log length and log speed are clipped to this range (log m, log m/s).
SAMPLE_LOG_RANGE = (-10.0, 10.0)
# Floor on box sides (m) before taking logs: non-positive sizes give a very low, finite value.
MIN_SIZE = 1e-6
# Above this standardised truncation point the normal tail is sampled as sqrt(a^2 + 2 E).
_TAIL_SWITCH = 8.0
# Proposals of a von Mises draw (`vonmises_from_uniforms`), all made at once: Best and
# Fisher's envelope accepts each with probability 0.66 or more, so all 24 fail with
# probability below 0.344^24 < 1e-11.
VONMISES_ATTEMPTS = 24
VONMISES_UNIFORMS = 2 * VONMISES_ATTEMPTS + 1  # each proposal's two, and the sign's
# Below this concentration the envelope's constant s is taken as 1 / kappa (float32).
_SMALL_KAPPA = 2e-2


# ----------------------------------------------------------------------------- von Mises
def log_i0(kappa: jnp.ndarray) -> jnp.ndarray:
    """log I0(kappa), stable for kappa in [0, 1e4+] via the scaled Bessel function i0e."""
    return jnp.log(special.i0e(kappa)) + kappa


def _mean_angle(direction: jnp.ndarray) -> jnp.ndarray:
    """Angle (rad) of a biternion [..., 2]; the zero vector maps to 0 with a finite gradient."""
    zero = (direction[..., 0] == 0.0) & (direction[..., 1] == 0.0)
    return jnp.arctan2(direction[..., 1], jnp.where(zero, 1.0, direction[..., 0]))


def vonmises_log_prob(angle: jnp.ndarray, direction: jnp.ndarray, log_kappa: jnp.ndarray):
    """Von Mises log density (1/rad) of `angle` (rad).

    Args:
      angle: [...] angle, rad (any real; the density is 2pi-periodic).
      direction: [..., 2] biternion (cos mu, sin mu) of the mean (its length is ignored).
      log_kappa: [...] log concentration.
    """
    kappa = jnp.exp(log_kappa)
    # kappa (cos d - 1) = -2 kappa sin^2(d / 2): accurate near the mode even at kappa = 1e4,
    # and with - log i0e(kappa) it equals kappa cos d - log I0(kappa) without cancellation.
    half = 0.5 * (angle - _mean_angle(direction))
    return -2.0 * kappa * jnp.sin(half) ** 2 - LOG_2PI - jnp.log(special.i0e(kappa))


def vonmises_from_uniforms(u: jnp.ndarray, direction: jnp.ndarray,
                           log_kappa: jnp.ndarray) -> jnp.ndarray:
    """One von Mises draw (rad: the mean plus an offset in [-pi, pi]) from uniforms `u`
    [VONMISES_UNIFORMS] in (0, 1).

    Best and Fisher's (1979) wrapped-Cauchy envelope with their exact acceptance test, as in
    distrax's and TensorFlow Probability's samplers, but with every proposal made at once and
    the first accepted one kept (the last if none is, a chance below 1e-11) instead of a loop
    that draws two more uniforms after each rejection: no loop under the sampler's vmap, and
    one PRNG call for the caller's whole draw (`uniforms`). The offset's sign is the last
    uniform's, independent of the acceptance test (the envelope is symmetric).
    """
    n = VONMISES_ATTEMPTS
    kappa = jnp.exp(log_kappa)
    exact = kappa > _SMALL_KAPPA
    c = jnp.where(exact, kappa, 1.0)  # no NaN in the unused branch
    r = 1.0 + jnp.sqrt(1.0 + 4.0 * c * c)
    rho = (r - jnp.sqrt(2.0 * r)) / (2.0 * c)
    s = jnp.where(exact, (1.0 + rho * rho) / (2.0 * rho), 1.0 / jnp.maximum(kappa, 1e-7))
    z = jnp.cos(jnp.pi * u[:n])  # cos(pi a), a uniform on (0, 1), as on (-1, 1)
    w = (1.0 + s * z) / (s + z)
    y = kappa * (s - w)
    accept = jnp.logical_not(y * jnp.exp(1.0 - y) < u[n:2 * n])  # NaN accepts, as distrax's
    i = jnp.where(jnp.any(accept), jnp.argmax(accept), n - 1)
    offset = jnp.arccos(jnp.clip(w[i], -1.0, 1.0))
    return _mean_angle(direction) + jnp.where(u[2 * n] < 0.5, -offset, offset)


def _pick(u: jnp.ndarray, logits: jnp.ndarray, tree):
    """Draws a component index from `logits` [K] with uniforms `u` [K] (`gumbel_argmax`) and
    gathers it from every leaf [K, ...]."""
    k = gumbel_argmax(u, logits)
    return k, tree_take(tree, k)


# ----------------------------------------------------------------------------- box
def _box_component_log_prob(z: jnp.ndarray, box: P.BoxParams) -> jnp.ndarray:
    """[K] bivariate normal log densities of z = (log w, log l)."""
    d = (z[None, :] - box.mu) * jnp.exp(-0.5 * box.log_var)
    one_m = 1.0 - box.rho**2
    quad = (d[:, 0] ** 2 - 2.0 * box.rho * d[:, 0] * d[:, 1] + d[:, 1] ** 2) / one_m
    return -LOG_2PI - 0.5 * jnp.sum(box.log_var, axis=-1) - 0.5 * jnp.log(one_m) - 0.5 * quad


def box_log_prob(raw: jnp.ndarray, size: jnp.ndarray) -> jnp.ndarray:
    """Log density of a box size under the bivariate log-normal mixture.

    Args:
      raw: [6K] raw box head output (see `params`).
      size: [2] (width, length), m; must be positive (floored at `MIN_SIZE`).

    Returns:
      Scalar log density over (width, length), log(1/m^2); includes the Jacobian 1/(w l).
    """
    box = P.split_box(raw)
    z = jnp.log(jnp.maximum(size, MIN_SIZE))
    comp = _box_component_log_prob(z, box)
    return special.logsumexp(jax.nn.log_softmax(box.logits) + comp) - jnp.sum(z)


def sample_box(key: jax.Array, raw: jnp.ndarray) -> jnp.ndarray:
    """Draws a box size [2] (width, length), m, from the mixture `raw` [6K]."""
    box = P.split_box(raw)
    k = box.logits.shape[0]
    u = uniforms(key, (k + 2,))  # the component's Gumbel noise, then two normals
    _, (mu, log_var, rho) = _pick(u[:k], box.logits, (box.mu, box.log_var, box.rho))
    sd = jnp.exp(0.5 * log_var)
    e = special.ndtri(u[k:])
    z = jnp.stack(
        [mu[0] + sd[0] * e[0], mu[1] + sd[1] * (rho * e[0] + jnp.sqrt(1.0 - rho**2) * e[1])]
    )
    return jnp.exp(jnp.clip(z, *SAMPLE_LOG_RANGE))


# ----------------------------------------------------------------------------- heading
def heading_log_prob(raw: jnp.ndarray, heading: jnp.ndarray) -> jnp.ndarray:
    """Log density (1/rad) of a heading (rad) under the von Mises mixture `raw` [4K]."""
    vm = P.split_heading(raw)
    comp = vonmises_log_prob(heading, vm.direction, vm.log_kappa)
    return special.logsumexp(jax.nn.log_softmax(vm.logits) + comp)


def sample_heading(key: jax.Array, raw: jnp.ndarray) -> jnp.ndarray:
    """Draws a heading, rad in [0, 2pi), from the von Mises mixture `raw` [4K]."""
    vm = P.split_heading(raw)
    k = vm.logits.shape[0]
    u = uniforms(key, (k + VONMISES_UNIFORMS,))  # the component's Gumbel noise, then the draw's
    _, (direction, log_kappa) = _pick(u[:k], vm.logits, (vm.direction, vm.log_kappa))
    return wrap_angle(vonmises_from_uniforms(u[k:], direction, log_kappa))


# ----------------------------------------------------------------------------- velocity
def _log_zero_speed(zero_speed) -> jnp.ndarray:
    # zero_speed = 0 means no truncation: log(1e-30) puts the cut ~70 log units below any mean.
    return jnp.log(jnp.maximum(zero_speed, 1e-30))


def velocity_log_prob(
    raw: jnp.ndarray,
    velocity: jnp.ndarray,
    heading: jnp.ndarray,
    relative: bool | jnp.ndarray,
    zero_speed: float,
) -> jnp.ndarray:
    """Log-likelihood of a velocity under the stationary + moving mixture `raw` [K + 5(K-1)].

    The measure is a point mass at v = 0 plus a density over the plane:
      * speed <= zero_speed (m/s): the actor is stationary and the value is log pi_0 exactly
        (a log probability, eq. 12 of the supplementary);
      * otherwise: log sum_{k>=1} pi_k LN_k(s | s > zero_speed) VM_k(omega) / s, a log
        density over (vx, vy) in log(1/(m/s)^2). The 1/s is the polar Jacobian from
        (s, omega) to (vx, vy). Each log-normal speed is truncated to s > zero_speed (divided
        by P_k(s > zero_speed)), so pi_0 + the integral over the plane is exactly 1 and the
        sampler below draws exactly this measure. With zero_speed = 0 it is eq. 13.

    Args:
      raw: [K + 5(K-1)] raw velocity head output (see `params`).
      velocity: [2] (vx, vy) over the ground, m/s.
      heading: actor heading, rad; used only when `relative`.
      relative: direction modelled relative to the heading (vehicles, bicyclists) or
        absolute (pedestrians). May be traced.
      zero_speed: speeds at or below this (m/s) are the stationary point mass (config field).
    """
    vp = P.split_velocity(raw)
    log_w = jax.nn.log_softmax(vp.logits)
    speed_sq = jnp.sum(velocity * velocity)
    moving = speed_sq > jnp.square(jnp.asarray(zero_speed, speed_sq.dtype))
    # Evaluate the moving branch at a safe point when stationary so no NaN gradient leaks.
    v = jnp.where(moving, velocity, jnp.array([1.0, 0.0], velocity.dtype))
    log_s = 0.5 * jnp.log(jnp.sum(v * v))
    omega = jnp.arctan2(v[1], v[0]) - jnp.where(relative, heading, 0.0)
    sigma = jnp.exp(vp.speed_log_sigma)
    z = (log_s - vp.speed_mu) / sigma
    log_normal = -0.5 * LOG_2PI - vp.speed_log_sigma - 0.5 * z * z
    # log P(s > zero_speed) of each component.
    log_tail = special.log_ndtr((vp.speed_mu - _log_zero_speed(zero_speed)) / sigma)
    # log LN(s) = log N(log s) - log s; the polar Jacobian adds another - log s.
    comp = log_normal - log_tail - 2.0 * log_s
    comp = comp + vonmises_log_prob(omega, vp.direction, vp.log_kappa)
    moving_lp = special.logsumexp(log_w[1:] + comp)
    return jnp.where(moving, moving_lp, log_w[0])


def velocity_proposal_score(
    raw: jnp.ndarray,
    velocity: jnp.ndarray,
    heading: jnp.ndarray,
    relative: bool | jnp.ndarray,
    zero_speed: float,
) -> jnp.ndarray:
    """Best-of-M score of a moving velocity proposal: its log density over (log speed,
    direction), the mixture's own coordinates. The density over (vx, vy) carries 1 / s^2,
    which would make the slowest proposal win. Meaningless for a stationary proposal (a
    probability, not a density): whether the actor moves is drawn once, with probability
    1 - pi_0 (`sampling.attributes.sample_attributes`)."""
    speed_sq = jnp.sum(velocity * velocity)
    tiny = jnp.finfo(speed_sq.dtype).tiny
    lp = velocity_log_prob(raw, velocity, heading, relative, zero_speed)
    return lp + jnp.log(jnp.maximum(speed_sq, tiny))


def _sample_std_normal_above(u: jnp.ndarray, a: jnp.ndarray) -> jnp.ndarray:
    """One standard normal draw conditioned on z > a (inverse CDF; Rayleigh tail for a > 8)
    from two uniforms `u` [2] in (0, 1)."""
    tiny = jnp.finfo(jnp.float32).tiny
    a_in = jnp.minimum(a, _TAIL_SWITCH)
    z_inv = -special.ndtri(jnp.maximum(u[0] * special.ndtr(-a_in), tiny))
    z_inv = jnp.maximum(z_inv, a_in)
    e = -jnp.log(u[1])  # a standard exponential
    a_tail = jnp.maximum(a, _TAIL_SWITCH)
    z_tail = jnp.sqrt(a_tail * a_tail + 2.0 * e)
    return jnp.where(a > _TAIL_SWITCH, z_tail, z_inv)


def sample_velocity(
    key: jax.Array,
    raw: jnp.ndarray,
    heading: jnp.ndarray,
    relative: bool | jnp.ndarray,
    zero_speed: float,
) -> jnp.ndarray:
    """Draws a velocity [2] (vx, vy), m/s, from the mixture `raw` [K + 5(K-1)].

    Component 0 gives exactly (0, 0); the others a speed > zero_speed (m/s) from the
    truncated log-normal and a direction (rad) from the von Mises, added to `heading` when
    `relative`. This is the measure scored by `velocity_log_prob`.
    """
    vp = P.split_velocity(raw)
    k = vp.logits.shape[0]
    # The component's Gumbel noise, the speed's two, then the direction's.
    u = uniforms(key, (k + 2 + VONMISES_UNIFORMS,))
    comp = gumbel_argmax(u[:k], vp.logits)
    j = jnp.maximum(comp - 1, 0)
    mu, log_sigma = vp.speed_mu[j], vp.speed_log_sigma[j]
    sigma = jnp.exp(log_sigma)
    a = (_log_zero_speed(zero_speed) - mu) / sigma
    log_s = mu + sigma * _sample_std_normal_above(u[k:k + 2], a)
    speed = jnp.exp(jnp.clip(log_s, *SAMPLE_LOG_RANGE))
    # Keep float32 rounding from landing a moving draw on the stationary side of the cut.
    speed = jnp.maximum(speed, jnp.asarray(zero_speed, speed.dtype) * (1.0 + 1e-5))
    omega = vonmises_from_uniforms(u[k + 2:], vp.direction[j], vp.log_kappa[j])
    omega = omega + jnp.where(relative, heading, 0.0)
    v = speed * jnp.stack([jnp.cos(omega), jnp.sin(omega)])
    return jnp.where(comp > 0, v, jnp.zeros_like(v))
