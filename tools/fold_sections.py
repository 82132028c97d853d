"""The exact fold count of one field, with its polylines as built and with every segment
split in two at its midpoint (the same rays, twice the vertices and so twice the
sections): how much the count depends on where the vertices lie, not only on the rays'
shapes (docs/performance.md, "The step at the near planes").

    .venv/bin/python tools/fold_sections.py RIG WIDTH HEIGHT METHOD QUALITY [plane=0]

RIG names a ``fixtures.rigs.<RIG>_rig``; ``plane=0`` builds without the step's bands at
the near planes (every gain 1).
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.methods.traced as traced  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.quality import fold_map  # noqa: E402


def halved(bundle):
    """``bundle`` (RayBundle) with a vertex added at the middle of every segment."""
    v, m = bundle.vertices, bundle.membership
    verts = np.empty((len(v), 2 * v.shape[1] - 1, 3), dtype=v.dtype)
    verts[:, 0::2], verts[:, 1::2] = v, 0.5 * (v[:, 1:] + v[:, :-1])
    mem = np.empty((len(m), 2 * m.shape[1] - 1), dtype=m.dtype)
    mem[:, 0::2], mem[:, 1::2] = m, 0.5 * (m[:, 1:] + m[:, :-1])
    return dataclasses.replace(bundle, vertices=verts, membership=mem)


def main(argv):
    rig, width, height, method, quality = argv[:5]
    opts = dict(a.split("=", 1) for a in argv[5:])
    if opts.get("plane") == "0":
        traced.plane_gains = lambda tracer_, rig_, *rest: [1.0] * (len(rig_.cameras) - 1)
    cams, masks = getattr(rigs, f"{rig}_rig")(int(width), int(height))
    settings = dataclasses.replace(settings_for(quality), processes=2)
    fld = prepare(Rig(cams, masks), method, settings)
    built, _stride = fold_map(fld, 2)
    rays = fld.rays
    fld.rays = lambda ix, iy: halved(rays(ix, iy))
    split, _stride = fold_map(fld, 1)
    print(
        f"{rig} {width}x{height} {method}->{fld.method} {quality} {opts}: folded quads as "
        f"built {int(built.sum())}, segments split in two {int(split.sum())}, "
        f"in both {int((built & split).sum())}"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
