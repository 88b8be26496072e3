"""Simulated drone captures with exact ground truth (the project's test and demo data).

Public API::

    SCENES                                   # names of the procedural scenes
    make_scene(name, seed) -> SimScene       # meshes, materials, distance helpers
    simulate_capture(name, n_views=60, width=320, height=240, seed=0, rings=None, ...)
        -> SimCapture (.capture: core.types.Capture, .scene: SimScene)
    simulate_stream(scene, fps, duration_s, width, height, seed)
        -> iterator of (stamp_ns, rgb, pose, mask)
"""

from .capture import (SCENES, STAMP_BASE_NS, SimCapture, SimConfig, make_scene, orbit_poses,
                      simulate_capture, simulate_stream, stream_pose)
from .render import Renderer, RenderResult, intrinsics_from_fov
from .scene import Part, Ring, SimScene

__all__ = ["SCENES", "STAMP_BASE_NS", "SimCapture", "SimConfig", "make_scene", "orbit_poses",
           "simulate_capture", "simulate_stream", "stream_pose", "Renderer", "RenderResult",
           "intrinsics_from_fov", "Part", "Ring", "SimScene"]
