"""The Cycles hand-off's OSL custom camera: its source, with the per-block ray sources
compiled in, and its compilation by Cycles' own compiler.

The source is a template in this package (``multiscale_camera.osl``, read when a shader
is made): ``shader_source`` fills in its tokens (``@BLOCK@`` and the like).
"""

import os

import numpy as np

from .cycles_rays import UNUSABLE_LIMIT, PinholeBlocks

# The custom camera's OSL template (packed with the extension).
OSL_PATH = os.path.join(os.path.dirname(__file__), "multiscale_camera.osl")


def cycles_module():
    """Cycles' compiled module ``_cycles``, or None where this Blender has no Cycles."""
    try:
        # here only: Cycles is optional (a Blender may be built without it), and its
        # absence is what ``cycles.unsupported_reason`` reports
        import _cycles
    except ImportError:
        return None
    return _cycles


def shader_source(blocks):
    """The OSL template (``OSL_PATH``) with the per-block ray sources of ``blocks``
    compiled in.

    Parameters
    ----------
    blocks : PinholeBlocks, or None for a shader that reads every ray from the tables.

    Returns
    -------
    str, OSL source.

    Raises
    ------
    OSError: the template cannot be read.
    """
    if blocks is None:
        blocks = PinholeBlocks(1, np.zeros((1, 1), dtype=np.int32), np.zeros((1, 18)))
    rows, cols = blocks.classes.shape
    # float32 literals with 9 significant digits read back to the same float32
    pinhole = ", ".join(f"{v:.9g}" for v in blocks.pinhole.astype(np.float32).ravel())
    values = {
        "@UNUSABLE_LIMIT@": repr(UNUSABLE_LIMIT),
        "@BLOCK@": str(blocks.size),
        "@BLOCKS_X@": str(cols),
        "@BLOCKS_Y@": str(rows),
        "@BLOCK_COUNT@": str(rows * cols),
        "@BLOCK_CLASS@": ",".join(map(str, blocks.classes.ravel().tolist())),
        "@PINHOLE_COUNT@": str(blocks.pinhole.size),
        "@PINHOLE@": pinhole,
    }
    with open(OSL_PATH, encoding="utf-8") as template:
        source = template.read()
    for token, value in values.items():
        source = source.replace(token, value)
    return source


def compile_shader(folder, blocks=None):
    """Compile ``shader_source(blocks)`` with Cycles' compiler.

    Parameters
    ----------
    folder : str, a writable folder for the source and the bytecode.
    blocks : PinholeBlocks or None (``shader_source``).

    Returns
    -------
    str, the OSO bytecode.

    Raises
    ------
    RuntimeError: the compiler failed (its messages go to the console).
    """
    source = os.path.join(folder, "multiscale_camera.osl")
    target = os.path.join(folder, "multiscale_camera.oso")
    with open(source, "w", encoding="utf-8") as out:
        out.write(shader_source(blocks))
    if not cycles_module().osl_compile(source, target):
        raise RuntimeError("the custom camera's OSL shader did not compile (see the console)")
    with open(target, encoding="utf-8") as oso:
        return oso.read()
