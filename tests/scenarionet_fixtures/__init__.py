"""Synthetic scenarios in the exact layouts ScenarioNet's converters write (for the tests),
one module per converter over the scene of `scene`, and two hand-made inputs (`simple`).

`BUILDERS` names every converter's fixture (`scene.Fixture`: the scenario and what importing
its default step must give).
"""

from .argoverse2 import argoverse2
from .nuplan import nuplan
from .nuscenes import nuscenes, nuscenes_keyframes
from .scene import Fixture, line_y, xyz
from .simple import hand_frame, standard_scenario
from .waymo import metadrive_legacy, waymo

BUILDERS = {
    "nuscenes": nuscenes,
    "nuscenes_keyframes": nuscenes_keyframes,
    "waymo": waymo,
    # no current_time_index in these: step 0 is imported by default
    "waymo_metadrive_S3": lambda: metadrive_legacy(waymo(ref=0), "S3"),
    "waymo_metadrive_S4": lambda: metadrive_legacy(waymo(ref=0), "S4"),
    "nuplan": nuplan,
    "argoverse2": argoverse2,
    "argoverse2_early": lambda: argoverse2(current=False),
}

__all__ = [
    "BUILDERS",
    "Fixture",
    "argoverse2",
    "hand_frame",
    "line_y",
    "metadrive_legacy",
    "nuplan",
    "nuscenes",
    "nuscenes_keyframes",
    "standard_scenario",
    "waymo",
    "xyz",
]
