"""Densities vs scipy, normalisation, samplers vs densities, masking and numerics."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy import special as sps
from scipy import stats

import scenegen_jax.distributions as D
from scenegen_jax.config import Config
from scenegen_jax.scene import BICYCLIST, PEDESTRIAN, STOP, VEHICLE, Actors, bin_index

K = 3
CFG = Config().replace(grid_size=8, m_per_px=2.0, num_mixtures=K, zero_speed=0.2)
N_BINS = CFG.grid.grid_size**2
TAU = 2.0 * np.pi


# ----------------------------------------------------------------------------- references
# Independent numpy readings of the layouts in `params` (they double as a layout test).
def np_box(raw, k):
    return dict(
        logw=sps.log_softmax(raw[:k]),
        mu=raw[k : 3 * k].reshape(k, 2),
        log_var=np.clip(raw[3 * k : 5 * k].reshape(k, 2), -10, 10),
        rho=np.tanh(raw[5 * k :]) * (1 - 1e-3),
    )


def np_heading(raw, k):
    cs = raw[k : 3 * k].reshape(k, 2)
    return dict(
        logw=sps.log_softmax(raw[:k]),
        loc=np.arctan2(cs[:, 1], cs[:, 0]),
        kappa=np.exp(np.clip(raw[3 * k :], -7, 9.3)),
    )


def np_velocity(raw, k):
    m = k - 1
    cs = raw[k + 2 * m : k + 4 * m].reshape(m, 2)
    return dict(
        logw=sps.log_softmax(raw[:k]),
        mu=raw[k : k + m],
        sigma=np.exp(np.clip(raw[k + m : k + 2 * m], -5, 5)),
        loc=np.arctan2(cs[:, 1], cs[:, 0]),
        kappa=np.exp(np.clip(raw[k + 4 * m :], -7, 9.3)),
    )


def vm_logpdf(theta, kappa, loc):
    wrapped = np.mod(theta - loc + np.pi, TAU) - np.pi + loc  # inside scipy's support
    return stats.vonmises.logpdf(wrapped, kappa, loc=loc)


def ref_box(raw, size, k):
    p, z = np_box(raw, k), np.log(size)
    comps = []
    for j in range(k):
        sd = np.exp(0.5 * p["log_var"][j])
        r = p["rho"][j]
        cov = [[sd[0] ** 2, r * sd[0] * sd[1]], [r * sd[0] * sd[1], sd[1] ** 2]]
        comps.append(p["logw"][j] + stats.multivariate_normal.logpdf(z, p["mu"][j], cov))
    return sps.logsumexp(comps) - z.sum()


def ref_heading(raw, theta, k):
    p = np_heading(raw, k)
    return sps.logsumexp(p["logw"] + vm_logpdf(theta, p["kappa"], p["loc"]), axis=-1)


def ref_velocity(raw, v, heading, relative, zero_speed, k):
    p = np_velocity(raw, k)
    s = np.hypot(v[0], v[1])
    if s <= zero_speed:
        return p["logw"][0]
    omega = np.arctan2(v[1], v[0]) - (heading if relative else 0.0)
    scale = np.exp(p["mu"])
    speed = stats.lognorm.logpdf(s, p["sigma"], scale=scale)
    speed = speed - stats.lognorm.logsf(zero_speed, p["sigma"], scale=scale)
    direction = vm_logpdf(omega, p["kappa"], p["loc"])
    return sps.logsumexp(p["logw"][1:] + speed + direction) - np.log(s)


def rand_box_raw(rng, k=K):
    mu = np.stack([np.log(rng.uniform(0.6, 3.0, k)), np.log(rng.uniform(1.0, 12.0, k))], 1)
    return np.concatenate(
        [rng.normal(0, 1.5, k), mu.ravel(), rng.uniform(-5, 1, 2 * k), rng.normal(0, 1.5, k)]
    ).astype(np.float32)


def rand_heading_raw(rng, k=K, log_kappa=(-7.0, 9.3)):
    return np.concatenate(
        [rng.normal(0, 1.5, k), rng.normal(0, 2, 2 * k), rng.uniform(*log_kappa, k)]
    ).astype(np.float32)


def rand_velocity_raw(rng, k=K):
    m = k - 1
    return np.concatenate(
        [
            rng.normal(0, 1.5, k),
            rng.uniform(-1.0, 2.5, m),
            rng.uniform(-2.5, 0.5, m),
            rng.normal(0, 2, 2 * m),
            rng.uniform(-3, 6, m),
        ]
    ).astype(np.float32)


def assert_close(actual, expected, rtol=1e-4, atol=1e-4):
    np.testing.assert_allclose(np.asarray(actual, np.float64), expected, rtol=rtol, atol=atol)


def vmap_lp(fn):
    """jit(vmap) over the value argument, params broadcast."""
    return jax.jit(jax.vmap(fn, in_axes=(None, 0)))


def draw(sample_fn, raw, n, seed):
    keys = jax.random.split(jax.random.key(seed), n)
    return np.asarray(jax.jit(jax.vmap(sample_fn, in_axes=(0, None)))(keys, jnp.asarray(raw)))


def normal_mixture_cdf(logw, mu, sd):
    w = np.exp(logw)
    return lambda x: np.sum(w * stats.norm.cdf((np.asarray(x)[:, None] - mu) / sd), axis=1)


def circular_cdf(logpdf):
    """CDF on [0, 2pi) of a circular log density, by cumulative trapezoid on a fine grid."""
    grid = np.linspace(0.0, TAU, 40001)
    pdf = np.exp(logpdf(grid))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(grid))])
    cdf /= cdf[-1]
    return lambda x: np.interp(np.mod(x, TAU), grid, cdf)


# ----------------------------------------------------------------------------- layouts
def test_layout_sizes_and_validation():
    sizes = (D.box_params_size, D.heading_params_size, D.velocity_params_size)
    assert tuple(f(10) for f in sizes) == (60, 40, 55)
    assert D.num_mixtures(jnp.zeros(18)) == 3
    with pytest.raises(ValueError):
        D.split_box(jnp.zeros(17))
    with pytest.raises(ValueError):
        D.split_velocity(jnp.zeros(6))  # a lone stationary component has no moving one
    # K = 1 (the paper's Table 2): velocity keeps the point mass and one moving component.
    assert tuple(f(1) for f in sizes) == (6, 4, 7)
    one = D.HeadOutputs(jnp.zeros(4), jnp.zeros(N_BINS), jnp.zeros(6), jnp.zeros(4), jnp.zeros(7))
    assert one.num_mixtures == 1
    head = D.HeadOutputs(
        jnp.zeros(4), jnp.zeros(N_BINS), jnp.zeros(18), jnp.zeros(12), jnp.zeros(12)
    )
    with pytest.raises(ValueError, match="disagree"):
        _ = head.num_mixtures
    assert len(jax.tree_util.tree_leaves(head)) == 5


# ----------------------------------------------------------------------------- vs scipy
def test_log_i0_stable_over_concentration_range():
    kappa = np.logspace(-3, 4, 57)
    got = D.log_i0(jnp.asarray(kappa, jnp.float32))
    assert_close(got, np.log(sps.i0e(kappa)) + kappa, rtol=1e-5, atol=1e-6)


def test_heading_matches_scipy_vonmises_mixture():
    rng = np.random.default_rng(0)
    raws = np.stack([rand_heading_raw(rng) for _ in range(12)])
    thetas = rng.uniform(0, TAU, (12, 6)).astype(np.float32)
    # Points near the modes of sharp components too.
    thetas[:, 0] = np.arctan2(raws[:, K + 1], raws[:, K]) + 0.003
    got = jax.jit(jax.vmap(vmap_lp(D.heading_log_prob)))(raws, thetas)
    want = [
        [ref_heading(r.astype(np.float64), t, K) for t in ts]
        for r, ts in zip(raws, thetas, strict=True)
    ]
    assert_close(got, np.array(want))


def test_box_matches_scipy_lognormal():
    rng = np.random.default_rng(1)
    raws = np.stack([rand_box_raw(rng) for _ in range(12)])
    sizes = np.stack([rng.uniform(0.5, 4, (12, 5)), rng.uniform(1, 15, (12, 5))], -1)
    got = jax.jit(jax.vmap(vmap_lp(D.box_log_prob)))(raws, sizes.astype(np.float32))
    want = [
        [ref_box(r.astype(np.float64), s, K) for s in ss] for r, ss in zip(raws, sizes, strict=True)
    ]
    assert_close(got, np.array(want))


@pytest.mark.parametrize("relative", [True, False])
def test_velocity_matches_scipy_lognormal_vonmises(relative):
    rng = np.random.default_rng(2)
    zero_speed = 0.5  # large enough that the truncation normaliser matters
    raws = np.stack([rand_velocity_raw(rng) for _ in range(12)])
    speeds = rng.uniform(0.51, 15, (12, 6))
    speeds[:, 0], speeds[:, 1] = 0.0, 0.49  # stationary: the point mass
    angles = rng.uniform(0, TAU, (12, 6))
    vs = np.stack([speeds * np.cos(angles), speeds * np.sin(angles)], -1).astype(np.float32)
    heading = np.float32(1.1)

    def lp(raw, v):
        return D.velocity_log_prob(raw, v, heading, relative, zero_speed)

    got = jax.jit(jax.vmap(vmap_lp(lp)))(raws, vs)
    want = [
        [ref_velocity(r.astype(np.float64), v, heading, relative, zero_speed, K) for v in vv]
        for r, vv in zip(raws, vs.astype(np.float64), strict=True)
    ]
    assert_close(got, np.array(want))
    log_pi0 = sps.log_softmax(raws[:, :K].astype(np.float64), axis=1)[:, :1]
    assert_close(got[:, :2], np.broadcast_to(log_pi0, (12, 2)), rtol=1e-6, atol=1e-6)


def test_location_and_hard_negative_match_numpy():
    rng = np.random.default_rng(3)
    logits = rng.normal(0, 3, N_BINS).astype(np.float32)
    full = sps.log_softmax(logits.astype(np.float64))
    for b in (0, 17, N_BINS - 1):
        area = CFG.grid.bin_area
        assert_close(D.location_log_prob(logits, b, area), full[b] - np.log(area))
        for n in (N_BINS, N_BINS + 5):
            assert_close(D.hard_negative_log_prob(logits, b, n), full[b], rtol=1e-6, atol=1e-6)
    weakest = int(np.argmin(logits))  # never in the top n unless forced
    for b in (weakest, int(np.argmax(logits)), 5):
        for n in (1, 7, 20):
            forced = logits.astype(np.float64).copy()
            forced[b] = np.inf
            top = np.argsort(-forced, kind="stable")[:n]
            want = logits[b] - sps.logsumexp(logits[top].astype(np.float64))
            got = jax.jit(D.hard_negative_log_prob, static_argnums=2)(logits, b, n)
            assert_close(got, want, rtol=1e-6, atol=1e-5)
    # Fewer bins in the normaliser can only raise the positive's probability.
    assert D.hard_negative_log_prob(logits, weakest, 7) > full[weakest]


def test_class_log_prob_and_masked_location():
    logits = jnp.array([1.0, -2.0, 0.5, 3.0])
    assert_close(D.class_log_prob(logits, STOP), sps.log_softmax(np.array(logits))[3])
    loc = np.random.default_rng(4).normal(size=N_BINS).astype(np.float32)
    mask = D.ordering_mask(10, N_BINS)
    lp, ok = D.masked_location_log_prob(loc, mask, 12, CFG.grid.bin_area)
    assert bool(ok)
    assert_close(lp, sps.log_softmax(loc[10:].astype(np.float64))[2] - np.log(CFG.grid.bin_area))
    assert D.masked_location_log_prob(loc, mask, 9, CFG.grid.bin_area)[0] == -np.inf


# ----------------------------------------------------------------------------- normalisation
def midpoints(lo, hi, n):
    h = (hi - lo) / n
    return lo + h * (np.arange(n) + 0.5), h


def test_box_density_integrates_to_one():
    raw = np.concatenate(
        [
            [0.3, -0.5, 0.1],
            np.log([[1.8, 4.5], [0.8, 1.8], [2.5, 12.0]]).ravel(),
            np.log(np.array([0.12, 0.15, 0.2, 0.1, 0.1, 0.18]) ** 2),
            [0.5, -0.3, 1.2],
        ]
    ).astype(np.float32)
    g, h = midpoints(0.0, 30.0, 1000)
    ww, ll = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([ww.ravel(), ll.ravel()], -1).astype(np.float32)
    mass = float(np.sum(np.exp(np.asarray(vmap_lp(D.box_log_prob)(raw, pts), np.float64))) * h * h)
    assert abs(mass - 1.0) < 1e-3, mass


def test_heading_density_integrates_to_one():
    raw = np.array([0.2, -1.0, 0.7, 1, 0, -0.3, 0.9, 0.5, -2, -3.0, np.log(200.0), 1.5], np.float32)
    g, h = midpoints(0.0, TAU, 20000)
    mass = float(np.sum(np.exp(np.asarray(vmap_lp(D.heading_log_prob)(raw, g.astype(np.float32))))))
    assert abs(mass * h - 1.0) < 1e-3, mass * h


VEL_RAW = np.array(
    # logits | mu log speed | log sigma | biternions | log kappa
    [0.4, 0.1, -0.2, np.log(4.0), np.log(8.0), -1.6, -1.9, 1, 0.2, -0.5, 1, np.log(3.0), 3.0],
    np.float32,
)


def test_velocity_point_mass_plus_density_integrates_to_one_cartesian():
    g, h = midpoints(-16.0, 16.0, 1000)
    vx, vy = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([vx.ravel(), vy.ravel()], -1).astype(np.float32)

    def lp(raw, v):
        return D.velocity_log_prob(raw, v, 0.4, True, CFG.grid.zero_speed)

    dens = np.exp(np.asarray(vmap_lp(lp)(VEL_RAW, pts), np.float64))
    moving = np.hypot(pts[:, 0], pts[:, 1]) > CFG.grid.zero_speed
    pi0 = np.exp(sps.log_softmax(VEL_RAW[:3].astype(np.float64))[0])
    total = pi0 + np.sum(dens[moving]) * h * h
    assert abs(total - 1.0) < 1e-3, total


def test_velocity_truncated_speed_normalised_in_polar_coordinates():
    zero_speed = 1.0  # cuts ~40% of the first component's log-normal mass
    raw = VEL_RAW.copy()
    raw[3:5] = [np.log(1.2), np.log(2.0)]
    raw[5:7] = np.log([0.6, 0.3])
    t, dt = midpoints(0.0, 5.0, 2000)  # log(s / zero_speed)
    w, dw = midpoints(-np.pi, np.pi, 256)
    tt, ww = np.meshgrid(t, w, indexing="ij")
    s = zero_speed * np.exp(tt.ravel())
    pts = np.stack([s * np.cos(ww.ravel()), s * np.sin(ww.ravel())], -1).astype(np.float32)

    def lp(r, v):
        return D.velocity_log_prob(r, v, 0.0, False, zero_speed)

    dens = np.exp(np.asarray(vmap_lp(lp)(raw, pts), np.float64))
    pi0 = np.exp(sps.log_softmax(raw[:3].astype(np.float64))[0])
    total = pi0 + np.sum(dens * s * s) * dt * dw  # dvx dvy = s ds dw = s^2 dt dw
    assert abs(total - 1.0) < 1e-3, total


def test_location_density_sums_to_one_over_region():
    logits = np.random.default_rng(5).normal(0, 4, N_BINS).astype(np.float32)
    bins = jnp.arange(N_BINS)
    lp = jax.vmap(D.location_log_prob, in_axes=(None, 0, None))(logits, bins, CFG.grid.bin_area)
    assert abs(float(jnp.sum(jnp.exp(lp))) * CFG.grid.bin_area - 1.0) < 1e-3
    mask = D.ordering_mask(20, N_BINS)
    mlp = jax.vmap(D.masked_location_log_prob, in_axes=(None, None, 0, None))(
        logits, mask, bins, CFG.grid.bin_area
    )[0]
    assert abs(float(jnp.sum(jnp.exp(mlp))) * CFG.grid.bin_area - 1.0) < 1e-3


# ----------------------------------------------------------------------------- samplers
N_DRAWS = 4000


def box_ks_pvalues(sizes, raw):
    p = np_box(raw.astype(np.float64), K)
    z = np.log(sizes)
    sd = np.exp(0.5 * p["log_var"])
    p_w = stats.kstest(z[:, 0], normal_mixture_cdf(p["logw"], p["mu"][:, 0], sd[:, 0])).pvalue
    # The sum log w + log l tests the correlation as well.
    sd_sum = np.sqrt(sd[:, 0] ** 2 + sd[:, 1] ** 2 + 2 * p["rho"] * sd[:, 0] * sd[:, 1])
    cdf = normal_mixture_cdf(p["logw"], p["mu"].sum(1), sd_sum)
    p_sum = stats.kstest(z.sum(1), cdf).pvalue
    return p_w, p_sum


def test_box_sampler_matches_density_and_wrong_scale_fails():
    raw = rand_box_raw(np.random.default_rng(6))
    raw[5 * K :] = [1.0, -0.8, 0.3]
    assert min(box_ks_pvalues(draw(D.sample_box, raw, N_DRAWS, 0), raw)) > 0.01
    wrong = raw.copy()
    wrong[3 * K : 5 * K] += 2 * np.log(1.25)  # every standard deviation x 1.25
    assert min(box_ks_pvalues(draw(D.sample_box, wrong, N_DRAWS, 0), raw)) < 1e-4


def test_heading_sampler_matches_density_and_shifted_mean_fails():
    # One component: circular mean direction and mean resultant length I1/I0.
    loc, kappa = 2.0, 4.0
    one = np.array([0.0, np.cos(loc), np.sin(loc), np.log(kappa)], np.float32)
    th = draw(D.sample_heading, one, N_DRAWS, 1)
    assert np.all((th >= 0) & (th < TAU + 1e-6))
    resultant = np.mean(np.exp(1j * th))
    assert abs(np.angle(resultant) - loc) < 0.03
    assert abs(np.abs(resultant) - sps.i1e(kappa) / sps.i0e(kappa)) < 0.015
    # Mixture: KS against the numerical CDF of the density.
    raw = np.array([0.5, -0.2, 0.0, 1, 0, -0.4, 0.9, 0.3, -1, 1.0, 3.0, -1.0], np.float32)
    cdf = circular_cdf(lambda g: ref_heading(raw.astype(np.float64), g[:, None], K))
    assert stats.kstest(draw(D.sample_heading, raw, N_DRAWS, 2), cdf).pvalue > 0.01
    wrong = raw.copy()
    shift = 0.15  # rad, every mean
    cs = wrong[K : 3 * K].reshape(K, 2)
    ang = np.arctan2(cs[:, 1], cs[:, 0]) + shift
    wrong[K : 3 * K] = np.stack([np.cos(ang), np.sin(ang)], 1).ravel()
    assert stats.kstest(draw(D.sample_heading, wrong, N_DRAWS, 2), cdf).pvalue < 1e-4


@pytest.mark.parametrize("kappa,wrong", [(0.005, 0.5), (0.3, 0.9), (4.0, 6.0), (300.0, 450.0)])
def test_vonmises_from_uniforms_matches_scipy_and_a_wrong_concentration_fails(kappa, wrong):
    """The block Best-Fisher draw against scipy's von Mises CDF, from below the small-kappa
    cut (2e-2: the envelope's constant is 1 / kappa there) to a concentration of 300; the
    same draws tested against another concentration are rejected."""
    from scenegen_jax.distributions.mixtures import VONMISES_UNIFORMS, vonmises_from_uniforms

    loc = 2.5
    direction = jnp.array([np.cos(loc), np.sin(loc)], jnp.float32)
    keys = jax.random.split(jax.random.key(int(kappa * 1000)), N_DRAWS)
    draws = jax.jit(
        jax.vmap(
            lambda k: vonmises_from_uniforms(
                D.uniforms(k, (VONMISES_UNIFORMS,)), direction, jnp.log(jnp.float32(kappa))
            )
        )
    )(keys)
    offset = np.asarray(draws, np.float64) - loc
    assert np.all(np.abs(offset) <= np.pi + 1e-5)
    assert stats.kstest(offset, stats.vonmises(kappa).cdf).pvalue > 0.01
    assert stats.kstest(offset, stats.vonmises(wrong).cdf).pvalue < 1e-4


def velocity_test_pvalues(v, raw, heading, zero_speed):
    p = np_velocity(raw.astype(np.float64), K)
    speed = np.hypot(v[:, 0], v[:, 1])
    stationary = speed == 0.0
    p_stat = stats.binomtest(int(stationary.sum()), len(v), np.exp(p["logw"][0])).pvalue
    s = speed[speed > zero_speed]
    if np.any((speed > 0) & (speed <= zero_speed)):
        return 0.0, 0.0, p_stat
    # Truncated log-normal mixture of the moving components, reweighted by their tails.
    a = (np.log(zero_speed) - p["mu"]) / p["sigma"]
    w = np.exp(p["logw"][1:])
    tail = stats.norm.sf(a)

    def speed_cdf(x):
        u = (np.log(np.asarray(x))[:, None] - p["mu"]) / p["sigma"]
        return np.sum(w * (stats.norm.cdf(u) - stats.norm.cdf(a)) / tail, 1) / w.sum()

    p_speed = stats.kstest(s, speed_cdf).pvalue
    omega = np.arctan2(v[speed > zero_speed, 1], v[speed > zero_speed, 0]) - heading

    def dir_logpdf(g):
        return sps.logsumexp(p["logw"][1:] + vm_logpdf(g[:, None], p["kappa"], p["loc"]), axis=1)

    p_dir = stats.kstest(np.mod(omega, TAU), circular_cdf(dir_logpdf)).pvalue
    return p_speed, p_dir, p_stat


def test_velocity_sampler_matches_density_and_untruncated_fails():
    zero_speed, heading = 1.0, 0.7
    raw = VEL_RAW.copy()
    raw[3:7] = [np.log(1.2), np.log(3.0), np.log(0.6), np.log(0.3)]

    def sampler(zs):
        return lambda key, r: D.sample_velocity(key, r, heading, True, zs)

    v = draw(sampler(zero_speed), raw, N_DRAWS, 3)
    assert np.all(np.isfinite(v))
    assert min(velocity_test_pvalues(v, raw, heading, zero_speed)) > 0.01
    # Sampling the plain log-normal (ignoring the cut) is caught by the same tests.
    v_wrong = draw(sampler(0.0), raw, N_DRAWS, 3)
    shifted = np.where(np.hypot(v_wrong[:, 0], v_wrong[:, 1])[:, None] <= zero_speed, 0, v_wrong)
    assert min(velocity_test_pvalues(shifted, raw, heading, zero_speed)) < 1e-4


def test_class_sampler_frequencies():
    logits = np.array([1.0, 0.2, -0.5, -1.0], np.float32)
    keys = jax.random.split(jax.random.key(4), 20000)
    cls = np.asarray(jax.vmap(D.sample_class, in_axes=(0, None))(keys, logits))
    counts = np.bincount(cls, minlength=4)
    want = np.exp(sps.log_softmax(logits.astype(np.float64))) * len(cls)
    assert stats.chisquare(counts, want).pvalue > 0.01
    wrong = np.exp(sps.log_softmax(logits.astype(np.float64) + [0, 0.1, 0, 0])) * len(cls)
    assert stats.chisquare(counts, wrong).pvalue < 1e-4


def test_location_sampler_respects_order_and_density():
    logits = np.random.default_rng(7).normal(0, 1, N_BINS).astype(np.float32)
    prev = 37
    mask = D.ordering_mask(prev, N_BINS)
    keys = jax.random.split(jax.random.key(5), 20000)
    fn = jax.jit(jax.vmap(lambda k: D.sample_location(k, logits, CFG.grid, mask)))
    bins, pos, ok = (np.asarray(x) for x in fn(keys))
    assert ok.all() and bins.min() >= prev
    np.testing.assert_array_equal(np.asarray(bin_index(pos, CFG.grid)), bins)
    counts = np.bincount(bins, minlength=N_BINS)[prev:]
    want = np.exp(sps.log_softmax(logits[prev:].astype(np.float64))) * len(bins)
    assert stats.chisquare(counts, want).pvalue > 0.01
    # Uniform inside the bin: x offset from the bin's left edge, in pixels.
    frac_x = (pos[:, 0] + CFG.grid.region_m / 2) / CFG.grid.m_per_px - bins % CFG.grid.grid_size
    frac_y = (CFG.grid.region_m / 2 - pos[:, 1]) / CFG.grid.m_per_px - bins // CFG.grid.grid_size
    assert min(stats.kstest(f, "uniform").pvalue for f in (frac_x, frac_y)) > 0.01


def test_bin_sampler_draws_the_categorical():
    """Row then column within it: the exact categorical, excluded bins (-inf) never drawn,
    a fully excluded row included."""
    rng = np.random.default_rng(9)
    width = 8
    log_probs = rng.normal(0, 1.5, 6 * width)
    log_probs[[3, 17, 40]] = -np.inf
    log_probs[16:24] = -np.inf  # row 2
    log_probs = sps.log_softmax(log_probs)
    fn = jax.jit(
        jax.vmap(lambda k: D.sample_bins(k, jnp.asarray(log_probs, jnp.float32), 4, width))
    )
    bins = np.asarray(fn(jax.random.split(jax.random.key(6), 10000))).ravel()
    assert bins.dtype == np.int32 and bins.shape == (40000,)
    counts = np.bincount(bins, minlength=log_probs.size)
    allowed = np.isfinite(log_probs)
    assert counts[~allowed].sum() == 0
    want = np.exp(log_probs[allowed]) * bins.size
    assert stats.chisquare(counts[allowed], want).pvalue > 0.01
    lp = log_probs[allowed]
    wrong = np.exp(sps.log_softmax(lp + 0.15 * (lp == lp.max())))  # the likeliest bin a bit more
    assert stats.chisquare(counts[allowed], wrong * bins.size).pvalue < 1e-4


def test_ordering_mask_with_nothing_left_is_finite():
    logits = jnp.full((N_BINS,), 1e4).at[3].set(-1e4)
    mask = D.ordering_mask(N_BINS, N_BINS)
    assert not bool(mask.any())

    def f(lg):
        return D.masked_location_log_prob(lg, mask, N_BINS - 1, CFG.grid.bin_area)[0]

    lp, ok = D.masked_location_log_prob(logits, mask, N_BINS - 1, CFG.grid.bin_area)
    assert not bool(ok) and lp == -np.inf
    assert np.all(np.isfinite(np.asarray(jax.grad(f)(logits))))
    b, pos, ok = D.sample_location(jax.random.key(0), logits, CFG.grid, mask)
    assert int(b) == N_BINS - 1 and not bool(ok) and np.all(np.isfinite(np.asarray(pos)))


# ----------------------------------------------------------------------------- best of M
def attribute_cases():
    rng = np.random.default_rng(8)
    mask = D.ordering_mask(9, N_BINS)
    return {
        "class": (D.sample_class, D.class_log_prob, rng.normal(size=4).astype(np.float32)),
        "location": (
            lambda k, lg: D.sample_location(k, lg, CFG.grid, mask),
            lambda lg, s: D.masked_location_log_prob(lg, mask, s[0], CFG.grid.bin_area)[0],
            rng.normal(size=N_BINS).astype(np.float32),
        ),
        "box": (D.sample_box, D.box_log_prob, rand_box_raw(rng)),
        "heading": (D.sample_heading, D.heading_log_prob, rand_heading_raw(rng, log_kappa=(0, 3))),
        "velocity": (
            lambda k, r: D.sample_velocity(k, r, 0.3, True, CFG.grid.zero_speed),
            lambda r, v: D.velocity_log_prob(r, v, 0.3, True, CFG.grid.zero_speed),
            rand_velocity_raw(rng),
        ),
    }


@pytest.mark.parametrize("name", ["class", "location", "box", "heading", "velocity"])
def test_best_of_m_picks_most_likely_draw(name):
    sample_fn, log_prob_fn, params = attribute_cases()[name]
    keys, m = jax.random.split(jax.random.key(9), 2), 6
    batched = jax.tree.map(lambda x: jnp.stack([x, x]), params)  # R = 2 examples
    best = jax.jit(lambda k, p: D.best_of_m(k, sample_fn, log_prob_fn, p, m))(keys, batched)
    sample_j, log_prob_j = jax.jit(sample_fn), jax.jit(log_prob_fn)
    for r in range(2):  # example r's proposals use split(keys[r], m)
        draws = [sample_j(k, params) for k in jax.random.split(keys[r], m)]
        lps = np.array([float(log_prob_j(params, d)) for d in draws])
        assert len(set(np.round(lps, 4))) > 1 or name == "class"  # draws actually differ
        want = draws[int(np.argmax(lps))]
        jax.tree_util.tree_map(lambda x, w, r=r: np.testing.assert_array_equal(x[r], w), best, want)
    one = jax.jit(lambda k, p: D.best_of_m(k, sample_j, log_prob_j, p, 1))(keys, batched)
    jax.tree_util.tree_map(
        lambda x, w: np.testing.assert_array_equal(x[0], w),
        one,
        sample_j(jax.random.split(keys[0], 1)[0], params),
    )


# ----------------------------------------------------------------------------- actor term
actor_ll = jax.jit(D.actor_log_likelihood, static_argnames=("cfg", "hard_negatives"))


def head_for(rng, loc_logits=None):
    return D.HeadOutputs(
        class_logits=jnp.asarray(rng.normal(size=4), jnp.float32),
        location_logits=jnp.asarray(
            rng.normal(size=N_BINS) if loc_logits is None else loc_logits, jnp.float32
        ),
        box=jnp.asarray(rand_box_raw(rng)),
        heading=jnp.asarray(rand_heading_raw(rng, log_kappa=(-1, 3))),
        velocity=jnp.asarray(rand_velocity_raw(rng)),
    )


def actor(cls, position=(3.1, -5.2), size=(1.9, 4.6), heading=0.8, velocity=(4.0, 1.5)):
    return Actors(
        cls=jnp.int32(cls),
        position=jnp.asarray(position, jnp.float32),
        size=jnp.asarray(size, jnp.float32),
        heading=jnp.float32(heading),
        velocity=jnp.asarray(velocity, jnp.float32),
        valid=jnp.bool_(True),
    )


def test_actor_log_likelihood_terms_and_masking():
    head = head_for(np.random.default_rng(10))
    tgt = actor(VEHICLE)
    full = actor_ll(head, tgt, False, CFG.model)
    train = actor_ll(head, tgt, False, CFG.model, hard_negatives=5)
    ped = actor_ll(head, actor(PEDESTRIAN), False, CFG.model)

    @jax.jit
    def reference(h, t):
        b = bin_index(t.position, CFG.grid)
        return {
            "vehicle": D.class_log_prob(h.class_logits, VEHICLE),
            "pedestrian": D.class_log_prob(h.class_logits, PEDESTRIAN),
            "location": D.location_log_prob(h.location_logits, b, CFG.grid.bin_area),
            "hard_negative": D.hard_negative_log_prob(h.location_logits, b, 5),
            "box": D.box_log_prob(h.box, t.size),
            "heading": D.heading_log_prob(h.heading, t.heading),
            "velocity": D.velocity_log_prob(h.velocity, t.velocity, t.heading, True, 0.2),
            "velocity_abs": D.velocity_log_prob(h.velocity, t.velocity, 0.0, False, 0.2),
        }

    ref = reference(head, tgt)
    for name in ("location", "box", "heading", "velocity"):
        assert_close(full[name], ref[name])
    assert_close(full["class"], ref["vehicle"])
    assert_close(train["location"], ref["hard_negative"] - np.log(CFG.grid.bin_area))
    assert float(train["location"]) > float(full["location"])
    for name in ("class", "box", "heading", "velocity"):
        assert_close(train[name], full[name], rtol=0, atol=0)

    assert float(ped["box"]) == 0.0 and float(ped["heading"]) == 0.0
    assert_close(ped["velocity"], ref["velocity_abs"])
    assert float(ped["velocity"]) != pytest.approx(float(ref["velocity"]))
    assert_close(ped["class"], ref["pedestrian"])

    relative = [bool(D.is_relative_direction(c)) for c in (VEHICLE, PEDESTRIAN, BICYCLIST)]
    assert relative == [True, False, True]
    bike = actor_ll(head, actor(BICYCLIST), False, CFG.model)
    assert_close(bike["velocity"], ref["velocity"])  # relative direction, like vehicles

    garbage = actor(VEHICLE, size=(0.0, np.nan), velocity=(np.nan, 0.0), heading=np.nan)
    for stop_target, flag in ((garbage, True), (actor(STOP), False)):
        stop = actor_ll(head, stop_target, flag, CFG.model, hard_negatives=5)
        assert_close(stop["class"], sps.log_softmax(np.asarray(head.class_logits))[STOP])
        assert all(float(stop[n]) == 0.0 for n in ("location", "box", "heading", "velocity"))
        g = total_grad(head, stop_target, flag)
        assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(g))
        assert not np.any(np.asarray(g.box)) and not np.any(np.asarray(g.location_logits))


def test_jit_equals_no_jit():
    head = head_for(np.random.default_rng(11))
    tgt = actor(VEHICLE)
    eager = D.actor_log_likelihood(head, tgt, False, CFG.model, hard_negatives=7)
    jitted = jax.jit(lambda h, t: D.actor_log_likelihood(h, t, False, CFG.model, hard_negatives=7))
    for name, value in jitted(head, tgt).items():
        assert_close(value, eager[name], rtol=1e-6, atol=1e-6)
    key = jax.random.key(12)
    for fn, raw in ((D.sample_box, head.box), (D.sample_heading, head.heading)):
        np.testing.assert_allclose(jax.jit(fn)(key, raw), fn(key, raw), rtol=1e-6)

    def v_fn(k, r):
        return D.sample_velocity(k, r, 0.3, True, CFG.grid.zero_speed)

    np.testing.assert_allclose(jax.jit(v_fn)(key, head.velocity), v_fn(key, head.velocity), 1e-6)


# ----------------------------------------------------------------------------- numerics
EXTREME_FILLS = {
    "+1e4": lambda n: np.full(n, 1e4),
    "-1e4": lambda n: np.full(n, -1e4),
    "alternating": lambda n: np.where(np.arange(n) % 2, 1e4, -1e4),
    "+-50": lambda n: np.where(np.arange(n) % 3, 50.0, -50.0),
    "zeros": lambda n: np.zeros(n),
}


@jax.jit
def total_value_and_grad(head, target, is_stop):
    """Sum of training and evaluation terms, and its gradient with respect to the head."""

    def total(h):
        train = D.actor_log_likelihood(h, target, is_stop, CFG.model, hard_negatives=9)
        evaluation = D.actor_log_likelihood(h, target, is_stop, CFG.model)
        return sum(train.values()) + sum(evaluation.values())

    return jax.value_and_grad(total)(head)


def total_grad(head, target, is_stop):
    return total_value_and_grad(head, target, is_stop)[1]


@jax.jit
def sample_all(key, head):
    return (
        D.sample_box(key, head.box),
        D.sample_heading(key, head.heading),
        D.sample_velocity(key, head.velocity, 0.5, True, CFG.grid.zero_speed),
        D.sample_location(key, head.location_logits, CFG.grid)[1],
        D.sample_class(key, head.class_logits),
    )


@pytest.mark.parametrize("fill", list(EXTREME_FILLS))
def test_extreme_parameters_give_finite_values_and_gradients(fill):
    f = EXTREME_FILLS[fill]
    head = D.HeadOutputs(
        *(jnp.asarray(f(n), jnp.float32) for n in (4, N_BINS, 6 * K, 4 * K, 6 * K - 5))
    )
    targets = [
        (actor(VEHICLE), False),
        (actor(VEHICLE, size=(1e-6, 1e3), velocity=(0.0, 0.0)), False),
        (actor(BICYCLIST, velocity=(0.2001, 0.0), heading=6.28), False),
        (actor(PEDESTRIAN, velocity=(1e3, -1e3)), False),
        (actor(STOP), True),
    ]

    for tgt, stop in targets:
        value, grads = total_value_and_grad(head, tgt, stop)
        assert np.isfinite(float(value)), (fill, tgt.cls)
        for leaf in jax.tree_util.tree_leaves(grads):
            assert np.all(np.isfinite(np.asarray(leaf))), (fill, tgt.cls)
    samples = sample_all(jax.random.key(0), head)
    assert all(np.all(np.isfinite(np.asarray(s))) for s in samples)


def test_check_grads_velocity_and_box_log_likelihood():
    rng = np.random.default_rng(13)
    with jax.enable_x64(True):
        v_raw = jnp.asarray(rand_velocity_raw(rng), jnp.float64)
        b_raw = jnp.asarray(rand_box_raw(rng), jnp.float64)
        v = jnp.array([2.0, -1.0], jnp.float64)

        @jax.jit
        def vel(raw):
            return D.velocity_log_prob(raw, v, 0.4, True, CFG.grid.zero_speed)

        @jax.jit
        def box(raw):
            return D.box_log_prob(raw, jnp.array([1.8, 4.4]))

        for f, raw in ((vel, v_raw), (box, b_raw)):
            check_grads(f, (raw,), order=1, modes=("rev",), eps=1e-4, atol=1e-5, rtol=1e-5)
