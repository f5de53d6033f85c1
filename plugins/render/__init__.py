"""Rendering reflectance textures on meshes (under construction: registers no stage until it is finished)."""
from btforge import hookimpl


@hookimpl
def btforge_stages():
    return []
