"""bpy -> numpy: the only place where Blender data becomes core data."""
