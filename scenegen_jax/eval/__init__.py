"""Likelihood scoring of real scenes, realism metrics and baselines."""
