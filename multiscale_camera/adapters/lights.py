"""Blender lights and world -> plain arrays for shading."""

import math
from dataclasses import dataclass

import numpy as np

from .meshes import uses_nodes
from .textures import environment_mean, equirectangular_uv, texture_from_node


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


@dataclass(frozen=True)
class World:
    """The world background, as the solid shading sees it.

    colour : (3,) float32 linear colour times strength (without a texture).
    texture : adapters.textures.Texture of an Environment Texture node feeding the
        Background colour (equirectangular), or None. strength : float.
    """

    colour: np.ndarray
    texture: object = None
    strength: float = 1.0

    def radiance(self, directions):
        """(P, 3) float64 background radiance along world directions (P, 3)."""
        if self.texture is None:
            return np.broadcast_to(self.colour.astype(np.float64), (len(directions), 3))
        return self.texture.sample(equirectangular_uv(directions)) * self.strength

    def ambient(self):
        """(3,) float64: radiance a white diffuse surface reflects under this world alone
        (its average over the sphere; unoccluded)."""
        if self.texture is None:
            return self.colour.astype(np.float64)
        return environment_mean(self.texture) * self.strength


def scene_world(scene, notices):
    """The scene's ``World`` (black without a world); an unreadable environment image
    adds a notice to ``notices`` (list of str)."""
    colour = world_colour(scene)
    world = scene.world
    if world is None or not uses_nodes(world):
        return World(colour)
    for node in world.node_tree.nodes:
        if node.type != "BACKGROUND":
            continue
        strength = float(node.inputs["Strength"].default_value)
        for link in node.inputs["Color"].links:
            if link.from_node.type == "TEX_ENVIRONMENT":
                texture = texture_from_node(link.from_node, notices)
                if texture is not None:
                    return World(colour, texture, strength)
        break
    return World(colour)
