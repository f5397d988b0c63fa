"""SceneGen in JAX/Flax: learn, sample and score traffic scenes from real driving logs."""

__version__ = "0.1.0"
