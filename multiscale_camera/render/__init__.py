"""Rendering the ray bundle: BVH march, shading, passes, and the RenderEngine."""
