"""One frame of a movie file as pixels, decoded by Blender's own FFmpeg.

``Image.pixels`` of a movie image gives its first frame whatever the scene's frame or
an image user says, and Python has no other way to a movie frame's pixels without a
GPU (``Image.gl_load(frame=...)`` needs one). Geometry nodes have one: their Image
Texture node takes the frame to read as an input. So a movie frame is read by a
temporary geometry-nodes object that puts one vertex at each pixel centre of the
movie's frame (a ``Points`` node, vertex index = row * width + column, row 0 at the
bottom), samples the movie there with *Closest* interpolation at that frame and stores
the colour on the vertices; its evaluated mesh gives them to numpy at once. The image,
node group, mesh, object and the scene evaluating it are made for the read and removed
at once: this changes Blender's data, so it happens on the main thread only.
"""

import bpy
import numpy as np

# The colour attribute the temporary object stores each pixel's colour in.
ATTRIBUTE = "multiscale_movie_rgba"
# The name of every temporary data-block of a read (Blender adds .001 etc. if taken).
TEMPORARY = "Multiscale movie frame"


def _math(nodes, links, operation, a, b=None, c=None):
    """A float Math node ``operation`` of ``a`` (a socket) and the constants or sockets
    ``b``, ``c``; its output socket."""
    node = nodes.new("ShaderNodeMath")
    node.operation = operation
    for slot, value in enumerate((a, b, c)):
        if value is None:
            continue
        if isinstance(value, bpy.types.NodeSocket):
            links.new(value, node.inputs[slot])
        else:
            node.inputs[slot].default_value = value
    return node.outputs[0]


def _frame_reader(image, number, width, height):
    """A geometry-nodes group whose output is ``width * height`` vertices (index =
    row * width + column, row 0 at the bottom) holding ``image``'s colour at frame
    ``number`` at each pixel centre in the float colour attribute ``ATTRIBUTE``."""
    group = bpy.data.node_groups.new(TEMPORARY, "GeometryNodeTree")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    index = nodes.new("GeometryNodeInputIndex").outputs[0]
    column = _math(nodes, links, "FLOORED_MODULO", index, float(width))
    row = _math(nodes, links, "FLOOR", _math(nodes, links, "DIVIDE", index, float(width)))
    uv = nodes.new("ShaderNodeCombineXYZ")
    links.new(_math(nodes, links, "MULTIPLY_ADD", column, 1 / width, 0.5 / width), uv.inputs[0])
    links.new(_math(nodes, links, "MULTIPLY_ADD", row, 1 / height, 0.5 / height), uv.inputs[1])
    texture = nodes.new("GeometryNodeImageTexture")
    texture.interpolation = "Closest"
    texture.extension = "EXTEND"
    texture.inputs["Image"].default_value = image
    texture.inputs["Frame"].default_value = number
    links.new(uv.outputs[0], texture.inputs["Vector"])
    points = nodes.new("GeometryNodePoints")
    points.inputs["Count"].default_value = width * height
    vertices = nodes.new("GeometryNodePointsToVertices")
    links.new(points.outputs[0], vertices.inputs[0])
    store = nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type, store.domain = "FLOAT_COLOR", "POINT"
    store.inputs["Name"].default_value = ATTRIBUTE
    links.new(vertices.outputs[0], store.inputs["Geometry"])
    links.new(texture.outputs["Color"], store.inputs["Value"])
    links.new(store.outputs[0], nodes.new("NodeGroupOutput").inputs[0])
    return group


def movie_frame(path, number):
    """(H, W, 4) float32 RGBA, row 0 at the top, of frame ``number`` of the movie file
    ``path`` (absolute), as Blender's image users number a movie's frames: from 1, the
    first shown for any number below 1 and the last for any number past the end. The
    values are those stored in the file (read as Non-Color, as ``Image.pixels`` gives
    an 8-bit image's). None when Blender cannot read the file (missing, not a movie
    its FFmpeg decodes). Main thread only (``movies`` module docstring)."""
    made = []
    try:
        try:
            image = bpy.data.images.load(path, check_existing=False)
        except RuntimeError:
            return None
        made.append((bpy.data.images, image))
        if image.source != "MOVIE":  # not a file type Blender plays as a movie
            return None
        width, height = image.size
        if width == 0 or height == 0 or image.frame_duration < 1:
            return None
        image.colorspace_settings.name = "Non-Color"
        group = _frame_reader(image, number, width, height)
        made.append((bpy.data.node_groups, group))
        mesh = bpy.data.meshes.new(TEMPORARY)
        made.append((bpy.data.meshes, mesh))
        obj = bpy.data.objects.new(TEMPORARY, mesh)
        made.append((bpy.data.objects, obj))
        obj.modifiers.new(TEMPORARY, "NODES").node_group = group
        scene = bpy.data.scenes.new(TEMPORARY)
        made.append((bpy.data.scenes, scene))
        scene.collection.objects.link(obj)
        layer = scene.view_layers[0]
        layer.update()  # the temporary scene's own depsgraph, evaluated
        colours = obj.evaluated_get(layer.depsgraph).data.attributes.get(ATTRIBUTE)
        if colours is None or len(colours.data) != width * height:
            return None
        rgba = np.empty(width * height * 4, dtype=np.float32)
        colours.data.foreach_get("color", rgba)
        return rgba.reshape(height, width, 4)[::-1]
    finally:
        for collection, block in reversed(made):
            collection.remove(block)
