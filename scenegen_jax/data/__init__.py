"""Readers (Argoverse 2, ScenarioNet) into Scene + VectorMap, and the preprocessing cache."""
