"""Blender lights and world -> plain arrays for shading."""

import math
from dataclasses import dataclass

import numpy as np

from .meshes import uses_nodes


@dataclass(frozen=True)
class Light:
    """One light, world space.

    kind : "SUN", "POINT", "SPOT" or "AREA".
    position : (3,) float64, world units (unused for SUN).
    direction : (3,) float64, unit vector the light points along (SUN, SPOT, AREA).
    colour : (3,) float64, linear colour times strength (W for point-like lights, W/m^2 for sun).
    spot_cos, spot_blend : cone half-angle cosine and blend (SPOT only).
    shadow : bool, whether the light casts shadows.
    """

    kind: str
    position: np.ndarray
    direction: np.ndarray
    colour: np.ndarray
    spot_cos: float = -1.0
    spot_blend: float = 0.0
    shadow: bool = True


def scene_lights(depsgraph):
    """The render-visible lights of an evaluated depsgraph."""
    lights = []
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type != "LIGHT":
            continue
        data = obj.data
        m = np.array(inst.matrix_world, dtype=np.float64)
        direction = -m[:3, 2] / np.linalg.norm(m[:3, 2])
        kind = data.type
        lights.append(
            Light(
                kind=kind,
                position=m[:3, 3].copy(),
                direction=direction,
                colour=np.array(data.color[:3], dtype=np.float64) * float(data.energy),
                spot_cos=math.cos(data.spot_size / 2) if kind == "SPOT" else -1.0,
                spot_blend=float(data.spot_blend) if kind == "SPOT" else 0.0,
                shadow=bool(getattr(data, "use_shadow", True)),
            )
        )
    return lights


def world_colour(scene):
    """(3,) float32 linear colour of the world background (Background node colour times
    strength when the world uses nodes, else the world colour; black without a world)."""
    world = scene.world
    if world is None:
        return np.zeros(3, dtype=np.float32)
    if uses_nodes(world):
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                colour = np.array(node.inputs["Color"].default_value[:3], dtype=np.float32)
                return colour * float(node.inputs["Strength"].default_value)
    return np.array(world.color[:3], dtype=np.float32)
