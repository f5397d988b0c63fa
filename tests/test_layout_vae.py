"""LayoutVAE: its densities against scipy, its Monte-Carlo likelihood against quadrature over
the latent, its scenes valid on real maps, and its training and shipping from the command
line."""

from __future__ import annotations

import collections
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.data.cache_write import write_cache
from scenegen_jax.data.sources import read_file, source_files, source_spec
from scenegen_jax.eval.layout_vae import layout_vae_scores, sample_layout_vae
from scenegen_jax.likelihood.host_data import layout_data
from scenegen_jax.model.layout_vae import (
    CLASS_ORDER,
    LayoutVAEConfig,
    gaussian2_log_prob,
    init_layout_vae,
    layout_arrays,
    poisson_log_prob,
    prior_params,
    step_log_likelihoods,
    step_log_probs,
)
from scenegen_jax.scene import NUM_CLASSES, in_region

TINY = get_config("tiny")


@pytest.fixture(scope="module")
def val_cache(tmp_path_factory, data_root):
    """A tiny-config cache of every 20th Argoverse 2 val frame, its source recorded."""
    spec = source_spec("av2", data_root, "val", 20)
    frames = [f for path in source_files(spec) for f in read_file(spec, path)[0]]
    path = str(tmp_path_factory.mktemp("layoutvae") / "val")
    write_cache(frames, path, TINY, collections.Counter(), source=spec)
    return load_cache(path)


def _cfg(latent: int = 2) -> LayoutVAEConfig:
    return LayoutVAEConfig(grid=TINY.grid, latent=latent, hidden=16, widths=(8, 8, 8))


def test_densities_are_scipys():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 2))
    raw = np.concatenate([rng.normal(size=(5, 2)), rng.normal(size=(5, 2)) * 0.3,
                          rng.normal(size=(5, 1))], -1)
    got = np.asarray(gaussian2_log_prob(jnp.asarray(x), jnp.asarray(raw)))
    for i in range(5):
        std, rho = np.exp(raw[i, 2:4]), 0.95 * np.tanh(raw[i, 4])
        cov = np.array([[std[0] ** 2, rho * std[0] * std[1]], [rho * std[0] * std[1],
                                                               std[1] ** 2]])
        want = stats.multivariate_normal(raw[i, :2], cov).logpdf(x[i])
        assert got[i] == pytest.approx(want, abs=1e-4)
    k, log_rate = np.array([0, 1, 7]), np.array([0.3, -1.0, 2.0])
    np.testing.assert_allclose(poisson_log_prob(jnp.asarray(k), jnp.asarray(log_rate)),
                               stats.poisson(np.exp(log_rate)).logpmf(k), atol=1e-5)


def test_a_standing_actor_is_a_point_mass():
    """A speed at or below zero_speed scores the probability of standing; a moving one that
    of moving times the Gaussian density, as SceneGen's velocity measure."""
    from scenegen_jax.model.layout_vae import actor_log_prob
    from scenegen_jax.scene import PEDESTRIAN

    out = jnp.asarray(np.random.default_rng(1).normal(size=19), jnp.float32)
    args = dict(cls=jnp.asarray(PEDESTRIAN), position=jnp.zeros(2), size=jnp.ones(2),
                heading=jnp.asarray(0.0), measured=jnp.asarray(False), grid=TINY.grid)
    base = actor_log_prob(out, velocity=jnp.zeros(2), **args)
    slow = actor_log_prob(out, velocity=jnp.array([0.1, 0.1]), **args)
    moving = actor_log_prob(out, velocity=jnp.array([3.0, -1.0]), **args)
    loc = gaussian2_log_prob(jnp.zeros(2), out[0:5]) - 2 * np.log(TINY.grid.region_m / 2)
    assert float(base - loc) == pytest.approx(float(jax.nn.log_sigmoid(out[18])), abs=1e-5)
    assert float(slow) == pytest.approx(float(base), abs=1e-6)
    gauss = gaussian2_log_prob(jnp.array([0.3, -0.1]), out[13:18]) - 2 * np.log(10.0)
    assert float(moving - loc) == pytest.approx(
        float(jax.nn.log_sigmoid(-out[18]) + gauss), abs=1e-4)


def test_layout_arrays_order_by_class_then_distance(val_cache):
    from scenegen_jax.data.cache import cached_actors

    actors = cached_actors(val_cache, 0)
    arr = layout_arrays(actors, TINY.grid)
    n = int(arr["valid"].sum())
    inside = np.asarray(actors.valid) & in_region(np.asarray(actors.position), TINY.grid)
    assert n == min(int(inside.sum()), TINY.grid.max_actors) > 0
    assert arr["valid"][:n].all() and not arr["valid"][n:].any()
    rank = [CLASS_ORDER.index(c) for c in arr["cls"][:n]]
    assert rank == sorted(rank)
    assert arr["counts"].sum() == n
    for c in CLASS_ORDER:
        d = np.linalg.norm(arr["position"][:n][arr["cls"][:n] == c], axis=1)
        assert np.all(np.diff(d) >= 0)


def test_monte_carlo_likelihood_agrees_with_quadrature(val_cache):
    """With a 2-d latent, log p(x_t | x_<t) = log of the integral of p(x_t | z) N(z; prior)
    over a 161 x 161 grid of +-6 prior standard deviations; the estimator's 20,000 samples
    agree with it per step."""
    cfg = _cfg(latent=2)
    params = init_layout_vae(cfg, seed=3)
    batch = {k: v[:1] for k, v in layout_data(val_cache, cfg.grid, [2], progress=False).items()}
    (mu_c, lv_c), (mu_a, lv_a) = prior_params(params, cfg, batch)
    t = np.linspace(-6, 6, 161)
    grid = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)  # [K, 2] in std

    def quadrature(mu, lv):
        std = np.exp(0.5 * np.asarray(lv))[..., None, :]
        z = np.asarray(mu)[..., None, :] + std * grid  # [..., K, 2]
        log_prior = stats.norm.logpdf(grid).sum(-1)  # density of the standardised grid
        cell = np.log((t[1] - t[0]) ** 2)
        return z, log_prior + cell

    zc, wc = quadrature(mu_c, lv_c)
    za, wa = quadrature(mu_a, lv_a)
    lp_c, lp_a = step_log_probs(params, cfg, batch, jnp.asarray(zc, jnp.float32),
                                jnp.asarray(za, jnp.float32))
    want_c = jax.scipy.special.logsumexp(np.asarray(lp_c, np.float64) + wc, -1)
    want_a = jax.scipy.special.logsumexp(np.asarray(lp_a, np.float64) + wa, -1)
    got_c, got_a = step_log_likelihoods(params, cfg, batch, jax.random.key(0), samples=20000)
    valid = batch["valid"][0]
    assert valid.sum() > 2
    np.testing.assert_allclose(np.asarray(got_c)[0], np.asarray(want_c)[0], atol=0.02)
    np.testing.assert_allclose(np.asarray(got_a)[0][valid], np.asarray(want_a)[0][valid],
                               atol=0.02)
    # 1,000 samples, as `evaluate` takes, are within 0.1 nats per step.
    got_c, got_a = step_log_likelihoods(params, cfg, batch, jax.random.key(1), samples=1000)
    np.testing.assert_allclose(np.asarray(got_a)[0][valid], np.asarray(want_a)[0][valid],
                               atol=0.1)


def test_scores_depend_on_the_scene_not_the_batch(val_cache):
    cfg = _cfg()
    params = init_layout_vae(cfg)
    a = layout_vae_scores(params, cfg, val_cache, samples=50, batch_size=3, progress=False)
    b = layout_vae_scores(params, cfg, val_cache, samples=50, batch_size=8, progress=False)
    np.testing.assert_allclose(a["scene_nll"], b["scene_nll"], rtol=1e-5)
    assert np.isfinite(a["scene_nll"]).all() and len(a["scene_nll"]) == len(val_cache)


def test_samples_are_valid_scenes(val_cache):
    cfg = _cfg()
    params = init_layout_vae(cfg, seed=1)
    data = layout_data(val_cache, cfg.grid, progress=False)
    egos = val_cache.ego(np.arange(len(val_cache)))
    scenes = sample_layout_vae(params, cfg, data["maps"], egos, seed=0)
    assert len(scenes) == len(val_cache)
    drawn = 0
    for s in scenes:
        v = s.valid
        drawn += int(v.sum())
        assert v.sum() <= cfg.max_actors
        assert np.isin(s.cls[v], np.arange(NUM_CLASSES)).all()
        assert np.all(in_region(s.position[v], cfg.grid))
        for field in ("position", "size", "heading", "velocity"):
            assert np.isfinite(getattr(s, field)[v]).all(), field
        assert np.all(s.size[v] > 0)
    assert drawn > 0
    again = sample_layout_vae(params, cfg, data["maps"], egos, seed=0)
    np.testing.assert_array_equal(again[3].position, scenes[3].position)


def test_train_baseline_command_trains_resumes_and_ships(val_cache, tmp_path, capsys, caplog):
    import shutil

    from scenegen_jax.cli import main
    from scenegen_jax.pretrained import PACKAGE_DIR, load_companion

    model = tmp_path / "model"
    shutil.copytree(f"{PACKAGE_DIR}/cpu-av2-womd", model,
                    ignore=shutil.ignore_patterns("layoutvae", "forecaster"))
    # A tiny-grid model to ship it with: its config is the preset the baseline names.
    args = ["train-baseline", "layoutvae", "--config", "tiny", "--data", val_cache.path,
            "--val-data", val_cache.path, "--workdir", str(tmp_path / "w"), "--batch-size",
            "4"]
    main([*args, "--steps", "2"])
    main([*args, "--steps", "3", "--out", str(model)])
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["step"] == 3 and np.isfinite(report["val_nll"]["scene_nll"])
    rows = [json.loads(line) for line in open(tmp_path / "w" / "metrics.jsonl")]
    assert [r["step"] for r in rows] == [2, 3]
    cfg, params, fields = load_companion(str(model), "layoutvae")
    assert cfg.grid == TINY.grid and fields["figures"]["val_nll"] == report["val_nll"]
    with pytest.raises(SystemExit):
        main([*args, "--steps", "3", "--lr", "0.01"])
    assert "run.json: field lr: the run there has 0.001, this one 0.01" in caplog.text
