"""The shading computes barycentrics only where something is interpolated (smooth corner
normals, texture UVs); mixed flat, smooth and textured hits shade as the plain formula
with barycentrics everywhere says."""

import numpy as np

from multiscale_camera.adapters.lights import Light, World
from multiscale_camera.adapters.meshes import Material, SceneGeometry
from multiscale_camera.adapters.textures import Texture
from multiscale_camera.render.raycast import Hits
from multiscale_camera.render.shade import shade, smooth_faces, textured_faces


def geometry():
    """Three triangles side by side in z = 0: flat and plain, smooth and plain, flat and
    textured."""
    rng = np.random.default_rng(3)
    verts, tris = [], []
    for k in range(3):
        verts += [(3.0 * k, 0, 0), (3.0 * k + 2, 0, 0), (3.0 * k, 2, 0)]
        tris.append((3 * k, 3 * k + 1, 3 * k + 2))
    normals = np.tile(np.array([0, 0, 1], np.float32), (3, 3, 1))
    tilted = rng.normal(size=(3, 3)) * 0.3 + (0, 0, 1)
    normals[1] = tilted / np.linalg.norm(tilted, axis=1, keepdims=True)
    texture = Texture(rng.random((4, 5, 3)).astype(np.float32))
    return SceneGeometry(
        vertices=np.array(verts, float),
        triangles=np.array(tris),
        colour=np.array([(0.8, 0.2, 0.1), (0.1, 0.7, 0.3), (0.5, 0.5, 0.5)], np.float32),
        pass_index=np.zeros(3, np.int32),
        object_of=np.zeros(3, np.int32),
        object_names=["mesh"],
        material=np.array([0, 0, 1], np.int32),
        materials=[Material(np.array([0.8, 0.2, 0.1])), Material(np.zeros(3), texture)],
        uv=rng.random((3, 3, 2)).astype(np.float32),
        normals=normals,
    )


def reference(geo, tri, points, sun):
    """Colour and normal of each hit by the plain formula: barycentrics on every hit,
    corner normals and UVs interpolated everywhere."""
    a, b, c = (geo.vertices[geo.triangles[tri, i]] for i in range(3))
    w = np.empty((len(tri), 3))
    for p in range(len(tri)):  # solve p = a + w1 (b - a) + w2 (c - a) point by point
        m = np.stack([b[p] - a[p], c[p] - a[p]], axis=1)
        w[p, 1:] = np.linalg.lstsq(m, points[p] - a[p], rcond=None)[0]
    w[:, 0] = 1 - w[:, 1] - w[:, 2]
    n = (geo.normals[tri] * w[:, :, None]).sum(1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    albedo = geo.colour[tri].astype(float)
    tex = geo.material[tri] == 1
    uv = (geo.uv[tri] * w[:, :, None]).sum(1)
    albedo[tex] = geo.materials[1].texture.sample(uv[tex])
    lambert = np.maximum(n @ -sun.direction, 0.0)[:, None] * sun.colour
    return albedo * (0.1 + lambert / np.pi), n


def test_barycentrics_only_where_interpolated_shade_as_everywhere():
    geo = geometry()
    assert smooth_faces(geo).tolist() == [False, True, False]
    assert textured_faces(geo).tolist() == [False, False, True]
    rng = np.random.default_rng(4)
    tri = rng.integers(0, 3, 60)
    u, v = rng.random(60) * 0.5, rng.random(60) * 0.5
    points = geo.vertices[geo.triangles[tri, 0]] + np.stack([2 * u, 2 * v, 0 * u], axis=1)
    down = np.tile([0.0, 0.0, -1.0], (60, 1))
    hits = Hits(np.ones(60, bool), tri, np.ones(60), points, down, 60)
    sun = Light("SUN", np.zeros(3), np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0), np.ones(3))
    world = World(np.full(3, 0.1, np.float32))
    for rows in [np.arange(60), *(np.flatnonzero(tri == k) for k in range(3)), tri != 0]:
        sub = Hits(*(x[rows] for x in (hits.hit, tri, hits.distance, points, down)), len(rows))
        out = shade(geo, sub, [sun], world, None, 1.0)
        colour, normal = reference(geo, tri[rows], points[rows], sun)
        np.testing.assert_allclose(out.colour, colour, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out.normal, normal, rtol=1e-5, atol=1e-6)
