"""Solid shading of first hits: base colour (a value or an image texture at the hit's UV)
times (world ambient + Lambert from the lights, on smooth normals where the faces are
smooth), plus emission, with straight shadow rays; misses show the world along the
ray's last direction. Radiometry follows Cycles' conventions: a diffuse surface of
albedo a under irradiance E has radiance a E / pi; a point light of power P radiates
P / (4 pi) W/sr, an area light P / pi cos(theta) W/sr, a sun gives E = strength."""

import math
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from ..core.geometry import dot3
from .raycast import cast_all, flat_triples, gc_paused, triangle_planes

# Shadow-ray origins are lifted off the surface by this fraction of the scene's size,
# enough to clear float32 BVH precision, far below anything visible.
SHADOW_OFFSET = 1e-5


def face_normals(geometry, triangles):
    """(T, 3) float64 unit geometric normals of the given triangle indices."""
    planes = triangle_planes(geometry)
    unit = planes.get("unit_normal")
    if unit is None:
        n = planes["normal"]
        unit = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
        planes["unit_normal"] = unit
    return unit[triangles]


def _spot_factor(light, to_light):
    cos = -dot3(to_light, light.direction)
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
    factor, to_light, distance = _irradiance_factor(light, points, normals)
    return factor[:, None] * light.colour, to_light, distance


def _irradiance_factor(light, points, normals):
    """``irradiance`` as (factor (P,), to_light, distance): e = factor * light.colour."""
    if light.kind == "SUN":
        to_light = np.broadcast_to(-light.direction, points.shape)
        distance = np.full(len(points), np.inf)
        cos = -dot3(normals, light.direction)
        return np.maximum(cos, 0.0, out=cos), to_light, distance
    vec = light.position - points
    distance = np.sqrt(dot3(vec, vec))
    to_light = vec / np.maximum(distance, 1e-12)[:, None]
    if light.kind == "AREA":
        falloff = np.maximum(-dot3(to_light, light.direction), 0.0) / (math.pi * distance**2)
    else:
        falloff = 1.0 / (4 * math.pi * distance**2)
        if light.kind == "SPOT":
            falloff = falloff * _spot_factor(light, to_light)
    cos = np.maximum(dot3(normals, to_light), 0.0)
    return cos * falloff, to_light, distance


def barycentric(geometry, triangles, points):
    """(P, 3) float64 barycentric weights of ``points`` (P, 3) on the given triangles."""
    planes = triangle_planes(geometry)
    v0, v1 = planes["e1"][triangles], planes["e2"][triangles]
    v2 = points - planes["a"][triangles]
    d00, d01, d11 = dot3(v0, v0), dot3(v0, v1), dot3(v1, v1)
    d20, d21 = dot3(v2, v0), dot3(v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    out = np.empty((len(triangles), 3))
    out[:, 1] = (d11 * d20 - d01 * d21) / den
    out[:, 2] = (d00 * d21 - d01 * d20) / den
    out[:, 0] = 1.0 - out[:, 1] - out[:, 2]
    return out


def albedo_and_emission(geometry, triangles, weights):
    """(albedo (P, 3), emission (P, 3)) float64 of hits on ``triangles`` at barycentric
    ``weights``: the material's base colour value, or its image texture at the hit's UV."""
    albedo = geometry.colour[triangles].astype(np.float64)
    emission = np.zeros((len(triangles), 3))
    if geometry.material is None or not geometry.materials:
        return albedo, emission
    mat = geometry.material[triangles]
    for m in np.unique(mat).tolist():
        material = geometry.materials[m]
        sel = np.flatnonzero(mat == m)
        if material.texture is not None:
            uv = (geometry.uv[triangles[sel]] * weights[sel, :, None]).sum(1)
            albedo[sel] = material.texture.sample(uv)
        if np.any(material.emission):
            emission[sel] = material.emission
    return albedo, emission


def smooth_faces(geometry):
    """(T,) bool, cached on the geometry: triangles whose corner normals differ (smooth
    shading), as opposed to flat ones, which carry their face normal at every corner."""
    planes = triangle_planes(geometry)
    smooth = planes.get("smooth")
    if smooth is None:
        nor = geometry.normals
        if nor is None or len(nor) == 0:
            smooth = np.zeros(len(planes["a"]), dtype=bool)
        else:
            smooth = (nor[:, 1] != nor[:, 0]).any(-1) | (nor[:, 2] != nor[:, 0]).any(-1)
        planes["smooth"] = smooth
    return smooth


def textured_faces(geometry):
    """(T,) bool, cached on the geometry: triangles whose material has an image texture."""
    planes = triangle_planes(geometry)
    textured = planes.get("textured")
    if textured is None:
        textured = np.zeros(len(planes["a"]), dtype=bool)
        if geometry.material is not None and geometry.materials:
            has = np.array([m.texture is not None for m in geometry.materials], dtype=bool)
            textured = has[geometry.material]
        planes["textured"] = textured
    return textured


def shading_normals(geometry, triangles, weights, geometric):
    """(P, 3) float64 unit shading normals: corner normals interpolated at ``weights``
    (equal to the face normal on flat faces); ``geometric`` where none are stored."""
    if geometry.normals is None or len(geometry.normals) == 0:
        return geometric
    n = np.einsum("pcj,pc->pj", geometry.normals[triangles], weights)
    length = np.sqrt(dot3(n, n))[:, None]
    return np.where(length > 1e-12, n / np.maximum(length, 1e-30), geometric)


@dataclass(frozen=True)
class Shaded:
    """colour : (R, 3) float32 linear RGB. normal : (R, 3) float32 world-space shading
    normal (zero for misses). casts : int, shadow rays cast."""

    colour: np.ndarray
    normal: np.ndarray
    casts: int


def shade(geometry, hits, lights, world, tree, scale, should_stop=None):
    """Linear RGB radiance of every ray.

    Parameters
    ----------
    geometry : SceneGeometry. hits : Hits of R rays. lights : list of Light.
    world : adapters.lights.World (its radiance for misses; its average as ambient light).
    tree : BVHTree for shadow rays. scale : float, scene size in world units.
    should_stop : callable, consulted every ``CASTS_PER_CHECK`` shadow rays.

    Returns
    -------
    Shaded
    """
    nrays = len(hits.hit)
    colour = np.zeros((nrays, 3), dtype=np.float32)
    normal = np.zeros((nrays, 3), dtype=np.float32)
    miss = np.flatnonzero(~hits.hit)
    if len(miss):
        colour[miss] = world.radiance(hits.direction[miss])
    idx = np.flatnonzero(hits.hit)
    if len(idx) == 0:
        return Shaded(colour, normal, 0)
    tri = hits.triangle[idx]
    points = hits.location[idx]
    n = face_normals(geometry, tri)
    # barycentrics only where something is interpolated: corner normals on smooth faces,
    # UVs under an image texture (flat, untextured faces need none)
    rounded = smooth_faces(geometry)[tri]
    need = rounded | textured_faces(geometry)[tri]
    weights = np.zeros((len(tri), 3))
    if need.all():
        weights = barycentric(geometry, tri, points)
    elif need.any():
        weights[need] = barycentric(geometry, tri[need], points[need])
    smooth = n
    if rounded.all():
        smooth = shading_normals(geometry, tri, weights, n)
    elif rounded.any():
        smooth = n.copy()
        smooth[rounded] = shading_normals(geometry, tri[rounded], weights[rounded], n[rounded])
    normal[idx] = smooth
    back = dot3(n, hits.direction[idx]) > 0
    sign = np.where(back, -1.0, 1.0)[:, None]
    facing = n * sign
    facing_smooth = smooth * sign
    albedo, emission = albedo_and_emission(geometry, tri, weights)
    light_sum = np.zeros((len(idx), 3))
    lifted = None
    casts = 0
    for light in lights:
        if not np.max(light.colour) > 0:
            continue  # no light from it, nothing to cast
        factor, to_light, distance = _irradiance_factor(light, points, facing_smooth)
        # light from behind the surface itself never reaches it
        lit = factor > 0
        if light.kind == "SUN":
            lit &= dot3(facing, light.direction) < 0
        else:
            lit &= dot3(facing, to_light) > 0
        if light.shadow and tree is not None:
            if lifted is None:
                lifted = points + facing * (SHADOW_OFFSET * scale)
            sun = -light.direction if light.kind == "SUN" else None
            blocked = _occluded(tree, lifted, to_light, distance, lit, should_stop, sun)
            casts += int(lit.sum())
            lit &= ~blocked
        light_sum += np.outer(factor * lit, light.colour)
    colour[idx] = albedo * (world.ambient() + light_sum / math.pi) + emission
    return Shaded(colour, normal, casts)


def _occluded(tree, origins, directions, distances, which, should_stop=None, parallel=None):
    """(P,) bool: whether a straight shadow ray from each origin hits anything before
    ``distances`` (only rays where ``which`` is True are cast). ``parallel`` : (3,) the
    one direction of every ray (a sun's), or None to take ``directions`` row by row."""
    blocked = np.zeros(len(origins), dtype=bool)
    sel = np.flatnonzero(which)
    n = len(sel)
    with gc_paused():
        if parallel is not None:  # a sun: one direction, and no end short of the scene's
            dirs = repeat(tuple(np.asarray(parallel, dtype=np.float64).tolist()), n)
            far = repeat(1e30, n)
        else:
            dirs = flat_triples(directions[sel])
            far = np.minimum(distances[sel], 1e30).tolist()
        tri = cast_all(tree.ray_cast, flat_triples(origins[sel]), dirs, far, should_stop)
    blocked[sel] = tri == tri  # not NaN: a hit
    return blocked
