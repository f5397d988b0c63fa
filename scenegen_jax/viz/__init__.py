"""Matplotlib renders of scenes and location heatmaps."""
