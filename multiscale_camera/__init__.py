"""Multiscale Camera: continuous multiscale images through bent camera rays.

Only ``register`` and ``unregister`` live here; bpy is imported when they run, so the
pure-numpy ``core`` package imports without Blender (the worker processes of
``core.runtime`` import this package and its core, and nothing else).
"""


def _modules():
    from .render import engine
    from .ui import live_picture, mask_overlay, operators, panels, preview, properties, volume

    return (properties, volume, operators, panels, preview, mask_overlay, live_picture, engine)


def register():
    for module in _modules():
        module.register()


def unregister():
    from .core import runtime

    for module in reversed(_modules()):
        module.unregister()
    runtime.shutdown()  # the worker processes end with the add-on
