"""Losses, the jitted train step, the training loop, checkpoints and sharding."""
