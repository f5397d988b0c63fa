"""Raw head-output layouts of the attribute heads and their split into constrained parameters.

Each attribute head of the model emits one flat float vector per actor. The layouts are
blocked (all logits, then all means, ...) and fixed here; nothing else in the library slices
raw head outputs. With K mixture components:

  box      [6K]          = [K logits | K*2 mu | K*2 log var | K raw rho]
           mu and log var are [K, 2] row-major over (log width, log length); rho = tanh(raw)
           * (1 - 1e-3) so the covariance stays positive definite.
  heading  [4K]          = [K logits | K*2 biternion (cos, sin) | K log kappa]
  velocity [K + 5(K-1)]  = [K logits | (K-1) mu of log speed | (K-1) log sigma of log speed |
                            (K-1)*2 direction biternion (cos, sin) | (K-1) direction log kappa]
           logit 0 is the stationary point mass (v = 0); component k >= 1 uses the k-1-th
           entry of every later block. The paper needs K >= 2 here but sweeps K = 1 in its
           Table 2: with K = 1, velocity keeps the point mass and one moving component
           (`velocity_components`), box and heading have one component.

Scales are clamped (`LOG_VAR_RANGE`, `LOG_SIGMA_RANGE`, `LOG_KAPPA_RANGE`) so extreme head
outputs give finite log-likelihoods and gradients; outside the range the gradient is zero.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from flax import struct

# Log variance of log width / log length: sigma in [6.7e-3, 148] (log m).
LOG_VAR_RANGE = (-10.0, 10.0)
# Log standard deviation of log speed: sigma in [6.7e-3, 148] (log m/s).
LOG_SIGMA_RANGE = (-5.0, 5.0)
# Log von Mises concentration: kappa in [9.1e-4, 1.1e4] (1/rad^2 near the mode).
LOG_KAPPA_RANGE = (-7.0, 9.3)
# |rho| <= 1 - 1e-3 keeps 1 - rho^2 >= 2e-3.
RHO_SCALE = 1.0 - 1e-3
# Avoids a zero-length biternion (no gradient singularity at the origin).
BITERNION_EPS = 1e-12


def box_params_size(k: int) -> int:
    """Length of the raw box head output for K components."""
    return 6 * k


def heading_params_size(k: int) -> int:
    """Length of the raw heading head output for K components."""
    return 4 * k


def velocity_components(k: int) -> int:
    """Velocity mixture components for the model's K: the stationary point mass and at least
    one moving component."""
    if k < 1:
        raise ValueError(f"need K >= 1 mixture components, got {k}")
    return max(k, 2)


def velocity_params_size(k: int) -> int:
    """Length of the raw velocity head output for the model's K (component 0 = v = 0)."""
    kv = velocity_components(k)
    return kv + 5 * (kv - 1)


# Initial spread of the moving components' mean log speed, log m/s (0.5 to 25 m/s).
INIT_LOG_SPEED_RANGE = (math.log(0.5), math.log(25.0))


def _spread_directions(n: int) -> np.ndarray:
    """[n, 2] unit biternions at angles 2 pi j / n, j = 0..n-1."""
    a = 2.0 * np.pi * np.arange(n) / n
    return np.stack([np.cos(a), np.sin(a)], axis=-1)


def _spread_log_kappa(n: int) -> float:
    """Log concentration whose angular spread (1 / sqrt(kappa)) equals the spacing 2 pi / n of
    n evenly spread components (clamped to `LOG_KAPPA_RANGE`)."""
    return float(np.clip(2.0 * math.log(n / (2.0 * math.pi)), *LOG_KAPPA_RANGE))


def initial_heading_bias(k: int) -> np.ndarray:
    """Initial bias [4K] of the raw heading output: equal weights, means evenly spread around
    the circle, each as wide as the spacing.

    The mixture then starts close to uniform (equal-weight, evenly spread components cancel
    every harmonic below the K-th), so the loss does not push the concentrations towards the
    floor of `LOG_KAPPA_RANGE`, where the clamp's gradient is zero and the direction's is
    proportional to kappa. From the first step the mixture weights act as a K-way classifier
    over directions, whose gradient does not vanish.
    """
    return np.concatenate(
        [np.zeros(k), _spread_directions(k).reshape(-1), np.full(k, _spread_log_kappa(k))]
    ).astype(np.float32)


def initial_velocity_bias(k: int) -> np.ndarray:
    """Initial bias of the raw velocity output (layout of `velocity_params_size`): equal
    weights; moving components with log speeds evenly spread over `INIT_LOG_SPEED_RANGE`,
    each as wide as the spacing, and directions spread as in `initial_heading_bias`."""
    m = velocity_components(k) - 1
    lo, hi = INIT_LOG_SPEED_RANGE
    mu = np.linspace(lo, hi, m) if m > 1 else np.array([0.5 * (lo + hi)])
    log_sigma = math.log((hi - lo) / m)
    return np.concatenate(
        [
            np.zeros(m + 1),
            mu,
            np.full(m, log_sigma),
            _spread_directions(m).reshape(-1),
            np.full(m, _spread_log_kappa(m)),
        ]
    ).astype(np.float32)



def _num_mixtures(raw: jnp.ndarray, per: int, offset: int, name: str) -> int:
    if raw.ndim != 1:
        raise ValueError(f"raw {name} params must be a flat vector (unbatched), got {raw.shape}")
    n = raw.shape[0] + offset
    if n % per or n // per < 1:
        raise ValueError(f"raw {name} params: length {raw.shape[0]} is not a valid layout size")
    return n // per


def num_mixtures(box_raw: jnp.ndarray) -> int:
    """K recovered from the length of a raw box vector [6K]."""
    return _num_mixtures(box_raw, 6, 0, "box")


@struct.dataclass
class BoxParams:
    """Constrained box-size mixture (bivariate log-normal over (width, length)).

    Attributes:
      logits: [K] unnormalised mixture logits.
      mu: [K, 2] means of (log width, log length), log m.
      log_var: [K, 2] clamped log variances of (log width, log length).
      rho: [K] correlation in (-1, 1).
    """

    logits: jnp.ndarray
    mu: jnp.ndarray
    log_var: jnp.ndarray
    rho: jnp.ndarray


@struct.dataclass
class VonMisesParams:
    """Constrained von Mises mixture over an angle.

    Attributes:
      logits: [K] unnormalised mixture logits.
      direction: [K, 2] unit biternion (cos mu, sin mu) of the mean angle.
      log_kappa: [K] clamped log concentration.
    """

    logits: jnp.ndarray
    direction: jnp.ndarray
    log_kappa: jnp.ndarray


@struct.dataclass
class VelocityParams:
    """Constrained velocity mixture: a point mass at v = 0 plus K-1 moving components.

    Attributes:
      logits: [K] unnormalised mixture logits, entry 0 is the stationary point mass.
      speed_mu: [K-1] mean of log speed, log m/s.
      speed_log_sigma: [K-1] clamped log standard deviation of log speed.
      direction: [K-1, 2] unit biternion of the mean direction.
      log_kappa: [K-1] clamped log concentration of the direction.
    """

    logits: jnp.ndarray
    speed_mu: jnp.ndarray
    speed_log_sigma: jnp.ndarray
    direction: jnp.ndarray
    log_kappa: jnp.ndarray


def unit_biternion(cs: jnp.ndarray) -> jnp.ndarray:
    """Normalises [..., 2] (cos, sin) pairs to unit length (finite gradient at 0)."""
    return cs * jnp.reciprocal(jnp.sqrt(jnp.sum(cs * cs, axis=-1, keepdims=True) + BITERNION_EPS))


def rotate_heading(raw: jnp.ndarray, cos: jnp.ndarray, sin: jnp.ndarray) -> jnp.ndarray:
    """Raw heading vectors [..., 4K] with every component's direction turned by the angle
    whose unit (cos, sin) is given per vector [...]: the mixture of `split_heading` turned
    by that angle (weights and concentrations unchanged; a rotation keeps the biternion's
    length, so `unit_biternion` commutes with it)."""
    k = raw.shape[-1] // 4
    if raw.shape[-1] != heading_params_size(k) or k < 1:
        raise ValueError(f"raw heading params: length {raw.shape[-1]} is not a valid layout size")
    d = raw[..., k : 3 * k].reshape(*raw.shape[:-1], k, 2)
    c, s = cos[..., None], sin[..., None]
    turned = jnp.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], axis=-1)
    return jnp.concatenate(
        [raw[..., :k], turned.reshape(*raw.shape[:-1], 2 * k), raw[..., 3 * k :]], axis=-1
    )


def split_box(raw: jnp.ndarray) -> BoxParams:
    """Splits and constrains a raw box vector [6K] (K from its length)."""
    k = _num_mixtures(raw, 6, 0, "box")
    return BoxParams(
        logits=raw[:k],
        mu=raw[k : 3 * k].reshape(k, 2),
        log_var=jnp.clip(raw[3 * k : 5 * k].reshape(k, 2), *LOG_VAR_RANGE),
        rho=jnp.tanh(raw[5 * k : 6 * k]) * RHO_SCALE,
    )


def split_heading(raw: jnp.ndarray) -> VonMisesParams:
    """Splits and constrains a raw heading vector [4K] (K from its length)."""
    k = _num_mixtures(raw, 4, 0, "heading")
    return VonMisesParams(
        logits=raw[:k],
        direction=unit_biternion(raw[k : 3 * k].reshape(k, 2)),
        log_kappa=jnp.clip(raw[3 * k : 4 * k], *LOG_KAPPA_RANGE),
    )


def split_velocity(raw: jnp.ndarray) -> VelocityParams:
    """Splits and constrains a raw velocity vector [K + 5(K-1)] (K >= 2, from its length)."""
    k = _num_mixtures(raw, 6, 5, "velocity")
    if k < 2:
        raise ValueError("raw velocity params: need K >= 2 (one stationary component)")
    m = k - 1
    return VelocityParams(
        logits=raw[:k],
        speed_mu=raw[k : k + m],
        speed_log_sigma=jnp.clip(raw[k + m : k + 2 * m], *LOG_SIGMA_RANGE),
        direction=unit_biternion(raw[k + 2 * m : k + 4 * m].reshape(m, 2)),
        log_kappa=jnp.clip(raw[k + 4 * m : k + 5 * m], *LOG_KAPPA_RANGE),
    )
