"""World-frame lights of a posed scan (``mode=scan``): every frame estimated, the lights fused in the world."""

from selfsup.scan.files import keyframes, scan_files, scene_points
from selfsup.scan.fuse import FusedLight, FuseOptions, WorldLight, fuse, fused_position, group_lights, world_lights

__all__ = ["scan_files", "keyframes", "scene_points", "FuseOptions", "FusedLight", "WorldLight", "fuse",
           "fused_position", "group_lights", "world_lights"]
