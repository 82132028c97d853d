"""Solid shading of first hits: base colour times (world ambient + Lambert from the lights),
with straight shadow rays. Radiometry follows Cycles' conventions: a diffuse surface of
albedo a under irradiance E has radiance a E / pi; a point light of power P radiates
P / (4 pi) W/sr, an area light P / pi cos(theta) W/sr, a sun gives E = strength."""

import math

import numpy as np

# Shadow-ray origins are lifted off the surface by this fraction of the scene's size,
# enough to clear float32 BVH precision, far below anything visible.
SHADOW_OFFSET = 1e-5


def face_normals(geometry, triangles):
    """(T, 3) float64 unit geometric normals of the given triangle indices."""
    tri = geometry.triangles[triangles]
    a, b, c = (geometry.vertices[tri[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def _spot_factor(light, to_light):
    cos = -(to_light @ light.direction)
    inner = light.spot_cos + (1.0 - light.spot_cos) * light.spot_blend
    t = np.clip((cos - light.spot_cos) / max(inner - light.spot_cos, 1e-9), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def irradiance(light, points, normals):
    """Unshadowed irradiance of ``light`` at surface points.

    Parameters
    ----------
    points, normals : (P, 3) float64; normals unit, facing the viewer.

    Returns
    -------
    e : (P, 3) float64, W/m^2 per colour channel.
    to_light : (P, 3) float64, unit direction to the light.
    distance : (P,) float64, distance to the light (inf for a sun).
    """
    if light.kind == "SUN":
        to_light = np.broadcast_to(-light.direction, points.shape)
        distance = np.full(len(points), np.inf)
        falloff = np.ones(len(points))
    else:
        vec = light.position - points
        distance = np.linalg.norm(vec, axis=-1)
        to_light = vec / np.maximum(distance, 1e-12)[:, None]
        if light.kind == "AREA":
            falloff = np.maximum(-(to_light @ light.direction), 0.0) / (math.pi * distance**2)
        else:
            falloff = 1.0 / (4 * math.pi * distance**2)
            if light.kind == "SPOT":
                falloff = falloff * _spot_factor(light, to_light)
    cos = np.maximum((normals * to_light).sum(-1), 0.0)
    return (cos * falloff)[:, None] * light.colour, to_light, distance


def shade(geometry, hits, lights, world, tree, scale):
    """Linear RGB radiance of every hit.

    Parameters
    ----------
    geometry : SceneGeometry. hits : Hits of R rays. lights : list of Light.
    world : (3,) float32, world colour (also the ambient light).
    tree : BVHTree for shadow rays. scale : float, scene size in world units.

    Returns
    -------
    colour : (R, 3) float32 linear RGB (the world colour for misses).
    normal : (R, 3) float32 world-space geometric normal (zero for misses).
    """
    nrays = len(hits.hit)
    colour = np.tile(np.asarray(world, dtype=np.float32), (nrays, 1))
    normal = np.zeros((nrays, 3), dtype=np.float32)
    idx = np.flatnonzero(hits.hit)
    if len(idx) == 0:
        return colour, normal
    tri = hits.triangle[idx]
    n = face_normals(geometry, tri)
    normal[idx] = n
    facing = np.where(((n * hits.direction[idx]).sum(-1) > 0)[:, None], -n, n)
    points = hits.location[idx]
    albedo = geometry.colour[tri].astype(np.float64)
    light_sum = np.zeros((len(idx), 3))
    lifted = points + facing * (SHADOW_OFFSET * scale)
    for light in lights:
        e, to_light, distance = irradiance(light, points, facing)
        lit = e.max(axis=-1) > 0
        if light.shadow and tree is not None:
            lit &= ~_occluded(tree, lifted, to_light, distance, lit)
        light_sum += e * lit[:, None]
    colour[idx] = albedo * (np.asarray(world, dtype=np.float64) + light_sum / math.pi)
    return colour, normal


def _occluded(tree, origins, directions, distances, which):
    """(P,) bool: whether a straight shadow ray from each origin hits anything before
    ``distances`` (only rays where ``which`` is True are cast)."""
    blocked = np.zeros(len(origins), dtype=bool)
    sel = np.flatnonzero(which)
    o = origins[sel].tolist()
    d = np.ascontiguousarray(directions[sel]).tolist()
    far = np.minimum(distances[sel], 1e30).tolist()
    cast = tree.ray_cast
    hit = [cast(o[i], d[i], far[i])[2] is not None for i in range(len(sel))]
    blocked[sel] = hit
    return blocked
