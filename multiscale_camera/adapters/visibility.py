"""Which objects a render's camera rays see: the one notion of visible that the rig
check (a viewport depsgraph), the render and the Cycles hand-off (a render depsgraph)
share, so that all three count the same objects (docs/failures.md, *Scene content*).

A render leaves out, for camera rays:

- objects disabled in renders (``hide_render``): their own, or their instancer's (an
  instance, a particle); an object disabled in renders still shows as a particle, not
  inside an instanced collection (as Blender 5's render depsgraph has them);
- objects in no collection the render shows: collections disabled in renders
  (``Collection.hide_render``, also through a parent collection) and collections
  excluded from the view layer (``LayerCollection.exclude``; a depsgraph never holds
  them);
- objects camera rays do not see: Object Properties > Visibility > Camera off
  (``visible_camera``), or in a collection set to Indirect Only;
- an instancer's own geometry where it does not show in renders
  (``show_instancer_for_render``).

Holdouts (``Object.is_holdout``, or a collection set to Holdout) are seen: they hide
what lies behind them and show transparent (alpha 0), as in Cycles.

A render's depsgraph already holds nothing disabled in renders; a viewport depsgraph
(the rig check's) holds those, and lacks what is hidden in the viewport only (disabled
in viewports, hidden with H, an instancer shown in renders only), which a render shows:
``camera_instances`` adds those back, unevaluated where the depsgraph did not evaluate
them (their modifiers then do not apply).
"""

from dataclasses import dataclass

import numpy as np

SHOWN = "SHOWN"
HOLDOUT = "HOLDOUT"


@dataclass(frozen=True)
class SeenObject:
    """One piece of geometry camera rays see.

    object : the (evaluated, when the depsgraph evaluated it) object whose data to read.
    matrix : (4, 4) float64 world matrix.
    kind : SHOWN or HOLDOUT.
    """

    object: object
    matrix: np.ndarray
    kind: str


def render_shown(scene):
    """set of str: full names of the objects a render of ``scene`` shows as far as
    collections go: those reached from the scene's collection through collections not
    disabled in renders (``Collection.hide_render``)."""
    shown, stack = set(), [scene.collection]
    while stack:
        coll = stack.pop()
        shown.update(o.name_full for o in coll.objects)
        stack.extend(c for c in coll.children if not c.hide_render)
    return shown


def camera_kind(obj, holder, view_layer, shown=None):
    """How a render's camera rays see ``obj`` (an original object), held in the scene by
    ``holder`` (itself, or the instancer of an instance): SHOWN, HOLDOUT, or None (left
    out). ``shown``: ``render_shown`` of the scene, for a viewport depsgraph, whose
    objects include those disabled in renders; None for a render's depsgraph."""
    if shown is not None:
        # a particle shows an object disabled in renders; an instanced collection does not
        own = obj.hide_render and (obj == holder or holder.instance_type == "COLLECTION")
        if own or holder.hide_render or holder.name_full not in shown:
            return None
    if not (obj.visible_camera and holder.visible_camera):
        return None
    if holder.indirect_only_get(view_layer=view_layer):
        return None
    if obj.is_holdout or holder.is_holdout or holder.holdout_get(view_layer=view_layer):
        return HOLDOUT
    return SHOWN


def shows_self(obj):
    """Whether a render shows ``obj``'s own geometry (an instancer's is shown only with
    ``show_instancer_for_render``)."""
    return not obj.is_instancer or obj.show_instancer_for_render


def camera_instances(depsgraph, types):
    """The objects of ``types`` (set of ``Object.type``) that a render of ``depsgraph``'s
    view layer shows to camera rays, instances and particles included.

    Yields
    ------
    SeenObject, each valid until the next is asked for (an instance's object is
    Blender's temporary, freed as the depsgraph's iteration moves on).
    """
    view_layer = depsgraph.view_layer
    viewport = depsgraph.mode == "VIEWPORT"
    shown = render_shown(depsgraph.scene.original) if viewport else None
    held = set()
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type not in types:
            continue
        original = obj.original
        instanced = inst.is_instance and inst.parent is not None
        holder = inst.parent.original if instanced else original
        if not instanced:
            held.add(original.name_full)
            # an instancer's own geometry (a particle emitter's, ...) as renders show it
            if not (shows_self(original) if viewport else inst.show_self):
                continue
        kind = camera_kind(original, holder, view_layer, shown)
        if kind is not None:
            yield SeenObject(obj, np.array(inst.matrix_world, dtype=np.float64), kind)
    if viewport:  # what the render shows and the viewport hides
        for original in view_layer.objects:
            if original.type not in types or original.name_full in held:
                continue
            if not shows_self(original):
                continue
            kind = camera_kind(original, original, view_layer, shown)
            if kind is None:
                continue
            obj = original.evaluated_get(depsgraph)
            matrix = np.array(obj.matrix_world, dtype=np.float64)
            yield SeenObject(obj, matrix, kind)
