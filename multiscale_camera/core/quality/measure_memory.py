"""Peak memory of measuring an IMAGE_BLEND field as AUTO measures its candidates: the
along-ray measure of each camera's preserved pixels (``report._preserved_in_blocks``) in
the main process, and the fold count's bands (``report.fold_map``), shared among worker
processes when there are enough of them. Part of the memory guard's arithmetic
(``memory``; docs/performance.md, "Peak memory").

Measured with ``tracemalloc`` on the zoom and three-camera rigs at 1920x1080 (IMAGE_BLEND,
STANDARD; ``bench/worker_memory.py ROW --measure``): the along-ray measure of 20,000 rays
held 53 and 93 MB (2 and 3 cameras: 10 and 18 vertices a ray), about 260 bytes a
vertex (each ray's curves in float64 and the measure's temporaries); a fold band of
1,036,800 vertices 122 and 145 MB, 118 and 142 bytes a vertex: the band's rays, its
vertex grid and ``quad_folds``' planes (about 70 bytes), and each camera's curve of
every ray blended (float64, 24 bytes a camera). Measured again at 218addd (the measure
on vertex planes in camera coordinates, the count on planes and its live sections):
the measure 40.8 and 71.0 MB (204 and 197 bytes a vertex), a band of 518,400 vertices
42.7 and 51.2 MB (82 and 99 bytes a vertex): the constants below, kept, overstate both
stages by about 30%, on the safe side. At 1920x1080 AUTO's main process peaks in the
weights' solve or their easing, where the measure's bytes do not count; a fold
worker's band does (two cameras: 61 MB estimated for a band measured at 43 MB), a
few percent of the build's estimate. Bands are cut as ``report.fold_map``
cuts them (``report.fold_plan``; smaller where an image has too few full bands for
its workers), so the bytes a vertex carry over to any band size. Shared, the count runs
in the workers while the main process measures (``report.measure_map``), which then
counts the bands no worker has taken: the measure, then a band, one after the other.
"""

from .metrics import MAX_MEASURED
from .report import fold_plan

ALONG_BYTES_PER_VERTEX = 260
FOLD_BYTES_PER_VERTEX = 70
FOLD_BYTES_PER_CAMERA_VERTEX = 24
# What a fold worker is sent of the field: the weights (float32) and the rig's masks
# (bool), per camera and pixel.
FIELD_BYTES_PER_CAMERA_PIXEL = 4 + 1
# ``geometry.DEFAULT_SEGMENTS``: IMAGE_BLEND's vertices per stage of a curve (the same
# value, tests/unit/test_memory_guard.py).
SEGMENTS = 8


def blend_vertices(cameras):
    """int, vertices of an IMAGE_BLEND ray: 1 + (N - 1) * segments + 1."""
    return 1 + (int(cameras) - 1) * SEGMENTS + 1


def measure_memory(width, height, cameras, workers=1):
    """Peak memory of measuring an IMAGE_BLEND field of ``cameras`` cameras at
    ``width`` x ``height`` pixels with ``workers`` worker processes available.

    Returns
    -------
    main : dict str -> int, bytes the main process adds while it measures (beyond the
        built field: its weights are the build's). worker : dict str -> int, one fold
        worker's bytes beyond its interpreter (empty when the bands stay here).
    workers : int, fold workers (0: none).
    """
    pixels = int(width) * int(height)
    k = blend_vertices(cameras)
    n, rows = fold_plan(width, height, k, workers)  # as ``report.fold_map``
    band = (
        min(rows, int(height))
        * int(width)
        * k
        * (FOLD_BYTES_PER_VERTEX + int(cameras) * FOLD_BYTES_PER_CAMERA_VERTEX)
    )
    along = min(MAX_MEASURED, pixels) * k * ALONG_BYTES_PER_VERTEX
    # the measure, then the bands (those no worker has taken), one after the other
    main = {"along-ray measure": along} if along >= band else {"fold band": band}
    if not n:
        return main, {}, 0
    field = pixels * int(cameras) * FIELD_BYTES_PER_CAMERA_PIXEL
    return main, {"field": field, "fold band": band}, n
