"""Operators ``multiscale.*``, registered together: the camera list (``camera_ops``),
masks (``mask_ops``, ``mask_make``), and the rig check, field, render, export and report
(``field_ops``)."""

import bpy

from . import camera_ops, field_ops, mask_make, mask_ops

CLASSES = camera_ops.CLASSES + field_ops.CLASSES + mask_ops.CLASSES + mask_make.CLASSES


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.app.handlers.save_pre.append(mask_ops.repack_masks)


def unregister():
    if mask_ops.repack_masks in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(mask_ops.repack_masks)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
