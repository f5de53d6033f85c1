"""Reading a scene into a self-contained :class:`~btforge.plugins.render.scene.Scene`: its spec checked, the mesh
files and environment maps it names read, and the checks that need built meshes."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .envmap import read_environment
from .geometry import build_mesh, point_inside, read_mesh_file
from .scene import Scene, SceneSpec, _absolute, _Where, parse_scene, read_scene_source


def load_scene(value: Any, paths) -> Scene:
    """Parse and check a scene (file path or mapping) and read every file it names into a :class:`Scene`."""
    data, source, base = read_scene_source(value, paths)
    spec = parse_scene(data, source, base)
    raw = _absolute(data, spec)
    arrays: dict[str, np.ndarray] = {}
    for mesh in spec.meshes:
        if mesh.file and f"{mesh.file}|positions" not in arrays:
            content = read_mesh_file(mesh.file, where=f"scene {source}, meshes.{mesh.name}.file")
            arrays.update({f"{mesh.file}|{k}": v for k, v in content.items()})
    for light in spec.lights:
        if light.file:
            arrays[f"{light.file}|pixels"] = read_environment(light.file, f"scene {source}, lights[{light.index}].file")
    scene = Scene(raw, source, arrays)
    check_scene_geometry(scene, spec)
    return scene


def check_scene_geometry(scene: Scene, spec: SceneSpec) -> None:
    """Checks that need the meshes: UVs where a texture is bound, point lights inside closed meshes.

    Meshes are built (the renderer builds its own) only for a scene with point lights, the one check that needs them.
    """
    w = _Where(spec.source)
    for mesh in spec.meshes:
        if mesh.file and mesh.material and scene.file_arrays(mesh.file)["corner_uv"].shape[0] == 0:
            raise w.error(f"meshes.{mesh.name}", f"binds material '{mesh.material}' but its mesh file has no UV "
                          f"coordinates: {Path(mesh.file).name}",
                          "export the mesh with texture coordinates (OBJ 'vt', PLY vertex u/v or s/t), or give it "
                          "a plain 'color' instead of a material")
    point_lights = [light for light in spec.lights if light.kind == "point"]
    built = {mesh.name: build_mesh(mesh, scene) for mesh in spec.meshes} if point_lights else {}
    for light in point_lights:
        for mesh in spec.meshes:
            b = built[mesh.name]
            if b.closed and point_inside(b, np.asarray(light.position)):
                raise w.error(f"lights[{light.index}].position",
                              f"point light at {list(light.position)} is inside the closed mesh '{mesh.name}'",
                              "it would light only the inside; move the light out of the mesh")
