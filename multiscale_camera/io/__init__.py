"""Reading and writing files (EXR tables, caches)."""
