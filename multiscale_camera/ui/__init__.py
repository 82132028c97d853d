"""Blender UI: scene properties, operators, the sidebar panel."""
