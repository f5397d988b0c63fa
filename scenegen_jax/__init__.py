"""SceneGen in JAX/Flax: learn, sample and score traffic scenes from real driving logs.

The top-level namespace is the Python API (`scenegen_jax.api`); it loads on first use, so
that `import scenegen_jax` stays cheap for the command line:

    import scenegen_jax as sg

    model = sg.load_model("cpu-av2-womd")
    scores = sg.score(model, "runs/av2_val")
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.2.0"

# name -> the module that defines it.
_EXPORTS = {
    "Model": "scenegen_jax.api",
    "Scores": "scenegen_jax.api",
    "load_model": "scenegen_jax.api",
    "load_data": "scenegen_jax.api",
    "prepare": "scenegen_jax.api",
    "train_model": "scenegen_jax.api",
    "score": "scenegen_jax.api",
    "sample": "scenegen_jax.api",
    "evaluate": "scenegen_jax.api",
    "render": "scenegen_jax.api",
    "Config": "scenegen_jax.config",
    "get_config": "scenegen_jax.config",
    "SamplerOptions": "scenegen_jax.sampling.rollout",
    "Recipe": "scenegen_jax.recipes",
    "get_recipe": "scenegen_jax.recipes",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'scenegen_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*__all__, "__version__"])
