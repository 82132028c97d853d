"""The hot loops keep to the core they run on: no BLAS call whose threads spin on the
other cores after it (numpy's OpenBLAS threads took the second core from the render's
tile loop: a cached 1920x1080 render took 10.6 s and 19.9 CPU seconds, 6.1 s and 6.3
without them)."""

import os
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from fixtures.rigs import three_camera_rig
from multiscale_camera.core.field import mask_weights
from multiscale_camera.core.field.solvers import _dot
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.quality import bending_active
from multiscale_camera.render.shade import _irradiance_factor

pytestmark = pytest.mark.skipif(
    not os.path.isdir("/proc/self/task") or (os.cpu_count() or 1) < 2,
    reason="per-thread CPU times need Linux's /proc, and spinning threads a second core",
)


def _other_threads_seconds():
    """CPU seconds used so far by each thread of this process but the calling one."""
    me = threading.get_native_id()
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir("/proc/self/task"):
        if int(tid) == me:
            continue
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[tid] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _settle(limit=3.0):
    """Wait until the other threads are idle (BLAS threads spin a while after a call)."""
    end = time.perf_counter() + limit
    last = _other_threads_seconds()
    while time.perf_counter() < end:
        time.sleep(0.2)
        now = _other_threads_seconds()
        if now == last:
            return
        last = now


def _others_busy(fn, seconds=0.6):
    """CPU seconds the process's other threads used while ``fn`` ran in a loop."""
    _settle()
    before = _other_threads_seconds()
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        fn()
    after = _other_threads_seconds()
    return sum(t - before.get(tid, 0.0) for tid, t in after.items())


@pytest.fixture(scope="module")
def detectable():
    """Skip unless a (P, 3) @ (3,) product here does set other threads spinning (a BLAS
    built single-threaded, or limited by OPENBLAS_NUM_THREADS, has nothing to show)."""
    a, v = np.random.default_rng(0).normal(size=(200_000, 3)), np.ones(3)
    busy = _others_busy(lambda: a @ v)
    if busy < 0.1:
        pytest.skip(f"BLAS products use no other thread here ({busy:.2f} CPU s)")
    return busy


def test_shading_lights_keeps_to_one_core(detectable):
    rng = np.random.default_rng(1)
    points = rng.normal(size=(50_000, 3))
    normals = rng.normal(size=(50_000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    down = np.array([0.0, 0.0, -1.0])
    lights = [
        SimpleNamespace(kind="SUN", direction=down, position=np.zeros(3)),
        SimpleNamespace(kind="AREA", direction=down, position=np.array([0.0, 0.0, 5.0])),
        SimpleNamespace(
            kind="SPOT",
            direction=down,
            position=np.array([0, 0, 5.0]),
            spot_cos=0.5,
            spot_blend=0.2,
        ),
    ]

    def shade_all():
        for light in lights:
            _irradiance_factor(light, points, normals)

    assert _others_busy(shade_all) < 0.1 * detectable


def test_family_evaluation_keeps_to_one_core(detectable):
    cams, _masks = three_camera_rig(96, 54)
    fam = Family(cams, 2)
    rng = np.random.default_rng(2)
    u, v, tau = rng.uniform(0, 96, 50_000), rng.uniform(0, 54, 50_000), rng.uniform(0, 2.5, 50_000)
    assert _others_busy(lambda: fam.evaluate(u, v, tau, jacobian=True)) < 0.1 * detectable


def test_fold_stretch_and_solver_products_keep_to_one_core(detectable):
    cams, _masks = three_camera_rig(96, 54)
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(200, 300, 3))
    a, b = rng.normal(size=1_000_000), rng.normal(size=1_000_000)

    def both():
        bending_active(vertices, cams[-1])
        _dot(a, b)

    assert _others_busy(both) < 0.1 * detectable


def test_image_blend_rays_keep_to_one_core(detectable):
    """IMAGE_BLEND's rays took their membership as a matrix product of the camera
    numbers and the weights, which woke BLAS's threads in every band of the fold count:
    1.4 to 1.5 CPU s for 0.9 s of wall time in one process at 480x270 on the
    three-camera rig, 0.9 CPU s without."""
    cams, masks = three_camera_rig(320, 180)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("PREVIEW"))
    iy, ix = np.mgrid[0:180, 0:320]
    ix, iy = ix.ravel(), iy.ravel()
    assert _others_busy(lambda: fld.rays(ix, iy)) < 0.1 * detectable


def test_mask_weights_solve_keeps_to_one_core(detectable):
    """The solve's coarsest grid was inverted by ``np.linalg.inv`` and applied by ``@``:
    both woke BLAS's threads, which spun through the whole solve (2.0 CPU s beside a
    3.0 s solve at 1920x1080, on the core the fold count's worker needs)."""
    _cams, masks = three_camera_rig(240, 135)
    masks = np.asarray(masks)
    assert _others_busy(lambda: mask_weights(masks)) < 0.1 * detectable


def test_mesh_gather_keeps_to_one_core(detectable):
    """A render's scene gather moved each mesh's vertices with ``@`` and inverted its
    matrix with ``np.linalg.inv``: both woke BLAS's threads (a product of 100,000 rows,
    and any inverse), once for every object, as the render's workers started."""
    import bpy

    from multiscale_camera.adapters.meshes import _mesh_arrays

    rng = np.random.default_rng(7)
    n = 60_000
    verts = rng.normal(size=(n, 3))
    faces = np.stack([np.arange(0, n - 2, 3), np.arange(1, n - 1, 3), np.arange(2, n, 3)], 1)
    mesh = bpy.data.meshes.new("blas_threads")
    mesh.from_pydata(verts.tolist(), [], faces.tolist())
    mesh.calc_loop_triangles()
    matrix = np.array(
        [[0.0, -2.0, 0.0, 1.0], [1.5, 0.0, 0.0, 2.0], [0.0, 0.3, 0.8, 3.0], [0, 0, 0, 1.0]]
    )
    try:
        co, _tris, _mat, _uv, normals = _mesh_arrays(mesh, matrix)
        stored = verts.astype(np.float32).astype(np.float64)  # a mesh's coordinates
        np.testing.assert_allclose(co, stored @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-12)
        corner = np.empty(len(mesh.loops) * 3, dtype=np.float32)
        mesh.corner_normals.foreach_get("vector", corner)
        want = corner.reshape(-1, 3).astype(np.float64) @ np.linalg.inv(matrix[:3, :3])
        want /= np.linalg.norm(want, axis=1, keepdims=True)
        np.testing.assert_allclose(normals.reshape(-1, 3), want, atol=1e-6)
        assert _others_busy(lambda: _mesh_arrays(mesh, matrix)) < 0.1 * detectable
    finally:
        bpy.data.meshes.remove(mesh)
