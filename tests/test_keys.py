"""One key scheme: a seed and a scene number give the same scene through `scenegen sample`,
`scenegen evaluate`'s sampler and the library, whatever the batch size; and the sampler and
the scorer compile once per model, not once per training setting."""

from __future__ import annotations

import collections
import json
import os

import jax
import numpy as np
import pytest

from scenegen_jax import cli
from scenegen_jax.checkpoint import Checkpointer
from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.data.cache_write import write_cache
from scenegen_jax.data.sources import read_frames, source_spec
from scenegen_jax.eval import nll
from scenegen_jax.eval.evaluate import real_scenes, sample_scenegen
from scenegen_jax.sampling import sample_scenes
from scenegen_jax.sampling.batch import jitted_sampler
from scenegen_jax.train.loop import save_or_check_config
from scenegen_jax.train.step import init_state

TINY = get_config("tiny")
NUM = 7  # scenes per request: not a multiple of 3 or 8, so the last batches are padded
SEED = 3


@pytest.fixture(scope="module")
def setup(tmp_path_factory, data_root):
    """A cache of real val frames and a workdir whose (untrained) model makes busy scenes."""
    cache_dir = str(tmp_path_factory.mktemp("keys_cache"))
    drops = collections.Counter()
    frames = read_frames(source_spec("av2", data_root, "val", 40), drops)
    write_cache(frames, cache_dir, TINY, drops)
    state = init_state(TINY)
    params = jax.tree.map(np.asarray, state.params)
    params["class_mlp2"]["bias"] = np.array([2.0, 0.5, 0.5, -2.0], np.float32)  # few stops
    workdir = str(tmp_path_factory.mktemp("keys_model"))
    save_or_check_config(workdir, TINY)
    ckpt = Checkpointer(os.path.join(workdir, "checkpoints"), every=1)
    ckpt.save(state._replace(params=params), force=True)
    ckpt.close()
    return load_cache(cache_dir), workdir, params


def _positions(actors) -> list[np.ndarray]:
    return [np.asarray(a.position)[np.asarray(a.valid)] for a in actors]


def test_same_seed_and_index_give_the_same_scene_everywhere(setup, tmp_path):
    cache, workdir, params = setup
    indices = np.arange(NUM) % len(cache)
    maps, scenes = real_scenes(cache, indices, TINY)
    egos = jax.tree.map(lambda *x: np.stack(x), *[s.ego for s in scenes])
    library = jax.device_get(sample_scenes(jax.random.key(SEED), params, TINY, maps, egos))
    want = [jax.tree.map(lambda x, j=j: x[j, 0], library.actors) for j in range(NUM)]
    assert sum(int(a.valid.sum()) for a in want) >= 2 * NUM  # scenes with actors to compare
    for batch in (1, 3, 8):
        got = sample_scenegen(params, TINY, maps, scenes, SEED, batch_size=batch)
        for a, b in zip(want, got, strict=True):
            for field in ("cls", "valid", "position", "size", "heading", "velocity"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        out = tmp_path / f"cli_{batch}"
        cli.main(["sample", "--workdir", workdir, "--data", cache.path, "--num", str(NUM),
                  "--seed", str(SEED), "--batch-size", str(batch), "--out", str(out)])
        with open(out / "scenes.jsonl") as f:
            rows = [json.loads(line) for line in f]
        for a, row in zip(want, rows, strict=True):
            xy = np.array([[r["x"], r["y"]] for r in row["actors"]], np.float32).reshape(-1, 2)
            np.testing.assert_array_equal(xy, _positions([a])[0])  # records in slot order


def test_training_settings_do_not_recompile_the_sampler_or_the_scorer(setup):
    cache, _, params = setup
    maps, scenes = real_scenes(cache, [0, 1], TINY)
    egos = jax.tree.map(lambda *x: np.stack(x), *[s.ego for s in scenes])
    changed = [TINY.replace(learning_rate=3e-4), TINY.replace(seed=5),
               TINY.replace(batch_size=2), TINY.replace(warmup_steps=10, name="other")]
    sample_scenes(jax.random.key(0), params, TINY, maps, egos, workers=1)
    nll.score_cache(params, cache, TINY, batch_size=2, progress=False, workers=1)
    compiled = (jitted_sampler()._cache_size(), nll._jitted_scorer.cache_info().currsize)
    for cfg in changed:
        sample_scenes(jax.random.key(1), params, cfg, maps, egos, workers=1)
        nll.score_cache(params, cache, cfg, batch_size=2, progress=False, workers=1)
    assert (jitted_sampler()._cache_size(), nll._jitted_scorer.cache_info().currsize) == compiled
    # A model field is a different program.
    sample_scenes(jax.random.key(1), params, TINY.replace(proposals=3), maps, egos, workers=1)
    assert jitted_sampler()._cache_size() == compiled[0] + 1
