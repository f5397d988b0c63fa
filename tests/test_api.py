"""The top-level Python API (`import scenegen_jax as sg`): the README's Python quick start
runs as written, and a model passed in the wrong place is a TypeError saying what was
expected."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO

import scenegen_jax as sg
from scenegen_jax.eval.nll import score_cache

SHARED_DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data"))


def readme_quick_start() -> str:
    """The fenced Python block under the README's "Quick start in Python" heading."""
    with open(os.path.join(REPO, "README.md")) as f:
        text = f.read()
    match = re.search(r"^## Quick start in Python\n.*?```python\n(.*?)```", text,
                      re.S | re.M)
    assert match, "README.md has no ```python block under '## Quick start in Python'"
    return match.group(1)


@pytest.fixture(scope="module")
def quick_start(tmp_path_factory, data_root):
    """The README's quick start, run as written but for where its files go (a temporary
    folder, not the repository's runs/ and out/) and where ../shared is."""
    tmp = tmp_path_factory.mktemp("quick_start")
    code = readme_quick_start()
    code = code.replace('"../shared/data', f'"{SHARED_DATA}')
    code = code.replace('"runs/', f'"{tmp}/runs/').replace('"out/', f'"{tmp}/out/')
    namespace: dict = {}
    exec(compile(code, "README.md quick start", "exec"), namespace)
    return namespace, tmp


def test_quick_start_runs_and_its_results_hold(quick_start):
    ns, tmp = quick_start
    model, cache, scores, scenes = ns["model"], ns["cache"], ns["scores"], ns["scenes"]
    assert isinstance(model, sg.Model) and model.config.name == "cpu"
    assert model.sampler == {"location_temperature": 0.7}
    assert len(cache) > 0 and cache.labels == ["av2:av2_val"]
    # The scores are the library's own, one scene NLL per cache scene, finite.
    direct = score_cache(model.params, cache, model.config, progress=False)
    assert set(direct) == set(scores.per_step)
    for k, v in direct.items():
        np.testing.assert_array_equal(v, scores.per_step[k])
    assert scores.scene_nll.shape == (len(cache),) and np.isfinite(scores.scene_nll).all()
    assert scores.summary()["scenes"] == len(cache)
    worst = scores.most_unusual(2)
    assert worst[0][2] >= worst[1][2]
    # Scenes sampled on the cache's maps, each with its map index; the same seed again gives
    # the same scenes.
    assert [s.index for s in scenes] == list(range(len(scenes)))
    again = sg.sample(model, cache, num_scenes=len(scenes), seed=0, batch_size=1)
    for a, b in zip(scenes, again, strict=True):
        np.testing.assert_array_equal(a.actors.position, b.actors.position)
    pngs = sorted(os.listdir(tmp / "out"))
    assert len(pngs) == len(scenes) and all(p.endswith(".png") for p in pngs)


def test_wrong_argument_order_is_a_type_error(quick_start):
    ns, _ = quick_start
    model, cache = ns["model"], ns["cache"]
    with pytest.raises(TypeError, match="expected a scenegen_jax.Model.*got CacheUnion"):
        sg.score(cache, model)
    with pytest.raises(TypeError, match="expected a scenegen_jax.Model.*got tuple"):
        sg.sample((model.config, model.params, {}), cache, num_scenes=1)
    with pytest.raises(TypeError, match="a second Model"):
        sg.score(model, model)
    with pytest.raises(TypeError, match="expected sampled scenes"):
        sg.render(model, [cache], "x.png")
    with pytest.raises(TypeError, match="prepare: expected the source kind first"):
        sg.prepare(model, "av2", "../shared/data/av2_sensor_mini", "x")
    with pytest.raises(TypeError, match="train_model: expected a Config or a preset name, "
                       "got a Model"):
        sg.train_model(model, cache.path, "w", 1)


def test_load_model_refuses_a_step_for_a_pretrained_model():
    with pytest.raises(ValueError, match="step selects a checkpoint"):
        sg.load_model("cpu-av2-womd", step=3)
    with pytest.raises(FileNotFoundError, match="installed"):
        sg.load_model("no-such-model")


def test_namespace_is_lazy_and_complete():
    # `import scenegen_jax` loads no JAX (the CLI restarts itself on tcmalloc first); every
    # name in __all__ resolves.
    code = ("import sys, scenegen_jax as sg; assert 'jax' not in sys.modules, 'jax loaded'; "
            "[getattr(sg, n) for n in sg.__all__]; print(len(sg.__all__))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert int(out.stdout) == len(sg.__all__) >= 10
    # A name of a sub-module would be shadowed by that module once anything imports it.
    package = os.path.dirname(sg.__file__)
    modules = {n.removesuffix(".py") for n in os.listdir(package)}
    assert not set(sg.__all__) & modules
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        sg.nope  # noqa: B018
