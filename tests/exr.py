"""Read Blender's multilayer EXR renders into numpy, whichever layout wrote them.

Blender 5 writes one part per pass ("ViewLayer.Combined", "ViewLayer.Object Index", ...);
older versions one part with channels "ViewLayer.Combined.R", "ViewLayer.IndexOB.X", ...
Both give the same result here. Pass names are as written, plus the other spelling of
the index passes ("IndexOB" and "Object Index" both work).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# Old and Blender 5 names of the same pass; both keys are filled in.
ALIASES = {"IndexOB": "Object Index", "IndexMA": "Material Index"}
CHANNEL_ORDER = "RGBAXYZWUV"


def _channel_key(name: str) -> tuple[int, str]:
    return (CHANNEL_ORDER.index(name) if name in CHANNEL_ORDER else len(CHANNEL_ORDER), name)


def read_passes(path: str | Path, layer: str | None = None) -> dict[str, np.ndarray]:
    """Return the passes of one view layer of a multilayer EXR.

    Parameters
    ----------
    path : str or Path
        The EXR file.
    layer : str, optional
        View layer name; by default the first one found.

    Returns
    -------
    dict of str to ndarray
        Pass name -> float32 array (H, W, C), row 0 at the top; channels in the order
        RGBA / XYZW (Combined is (H, W, 4), Depth (H, W, 1), Normal (H, W, 3)).
        A file without layers ("R", "G", "B", "A" channels) gives one pass, "Combined".
    """
    import OpenEXR

    channels: dict[str, np.ndarray] = {}
    for part in OpenEXR.File(str(path), separate_channels=True).parts:
        for name, channel in part.channels.items():
            channels[name] = channel.pixels

    grouped: dict[str, dict[str, np.ndarray]] = {}
    for name, pixels in channels.items():
        *prefix, channel = name.split(".")
        if len(prefix) >= 2:  # layer.pass.channel; a layer name may hold dots
            found_layer, pass_name = ".".join(prefix[:-1]), prefix[-1]
        else:  # "pass.channel" or a plain "R"
            found_layer, pass_name = "", prefix[0] if prefix else "Combined"
        if layer is None:
            layer = found_layer
        if found_layer == layer:
            grouped.setdefault(pass_name, {})[channel] = pixels
    if not grouped:
        raise KeyError(f"{path}: no view layer {layer!r}")

    passes = {
        name: np.stack([chans[c] for c in sorted(chans, key=_channel_key)], axis=-1).astype(
            np.float32
        )
        for name, chans in grouped.items()
    }
    for old, new in ALIASES.items():
        if old in passes or new in passes:
            passes[old] = passes[new] = passes.get(old, passes.get(new))
    return passes
