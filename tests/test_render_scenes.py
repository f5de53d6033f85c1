"""Scene files: bad scenes are refused at graph validation, before anything runs; scene.read; image.write."""
from pathlib import Path

import numpy as np
import pytest
import yaml

import btforge
from btforge.errors import BtforgeInputError
from btforge.graph import check_graph, load_graph
from btforge.registry import default_registry

GOOD = {
    "camera": {"type": "orthographic", "width": 16, "height": 16, "position": [0, 0, 5], "look_at": [0, 0, 0],
               "extent": 2.0},
    "meshes": {"ground": {"primitive": "plane", "size": 2.0, "material": "stone"}},
    "lights": [{"type": "directional", "direction": [0.3, 0.2, 0.93], "intensity": 1.0}],
    "effects": ["shadows"],
}


def graph_with(tmp_path: Path, scene: dict, wire: bool = True) -> Path:
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))
    nodes = {
        "material": {"stage": "demo.material", "params": {"size": [16, 16], "lights": 8}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "material.stack"}},
        "img": {"stage": "render.image", "params": {"scene": "scene.yaml"}},
    }
    if wire:
        nodes["img"]["inputs"] = {"stone": "fit.model"}
    path = tmp_path / "graph.yaml"
    path.write_text(yaml.safe_dump({"nodes": nodes}))
    return path


def validate(path: Path):
    return check_graph(load_graph(path), default_registry(), path.parent)


def with_changes(**changes) -> dict:
    scene = yaml.safe_load(yaml.safe_dump(GOOD))
    for key, value in changes.items():
        target = scene
        *parents, last = key.split("__")
        for p in parents:
            target = target[int(p)] if isinstance(target, list) else target[p]
        target[last] = value
    return scene


def test_good_scene_validates_with_one_port_per_material(tmp_path):
    from btforge.stages import RunPaths
    checked = validate(graph_with(tmp_path, GOOD))
    ports = checked.stages["img"].input_ports(checked.params["img"], RunPaths(tmp_path, tmp_path))
    assert ports == {"scene_data": "Scene", "stone": "ReflectanceModel"}


BAD = {
    "missing mesh file": (dict(meshes={"ground": {"file": "nowhere.ply", "material": "stone"}}),
                          "mesh file not found: .*nowhere.ply"),
    "unknown effect": (dict(effects=["shadow"]), "unknown effect 'shadow'.*did you mean 'shadows'"),
    "zero direction": (dict(lights__0__direction=[0, 0, 0]), "lights\\[0\\].direction: expected a non-zero direction"),
    "NaN direction": (dict(lights__0__direction=[float("nan"), 0, 1]), "lights\\[0\\].direction: expected finite"),
    "negative intensity": (dict(lights__0__intensity=-1.0), "lights\\[0\\].intensity: expected a non-negative"),
    "negative colour": (dict(lights__0__intensity=[1, -0.1, 1]), "expected non-negative values"),
    "unknown mesh key": (dict(meshes__ground__materail="stone"), "meshes.ground.materail: unknown key.*'material'"),
    "camera up along view": (dict(camera__up=[0, 0, 1]), "camera.up: is parallel to the viewing direction"),
    "missing environment map": (dict(lights=[{"type": "environment", "file": "sky.exr"}]),
                                "environment map not found: .*sky.exr"),
    "point light inside a sphere": (
        dict(meshes={"ground": {"primitive": "plane", "material": "stone"},
                     "ball": {"primitive": "sphere", "radius": 0.5, "position": [0, 0, 1]}},
             lights=[{"type": "point", "position": [0.1, 0, 1.1], "intensity": 1.0}]),
        "point light at \\[0.1, 0.*, 1.1\\] is inside the closed mesh 'ball'"),
    "unknown primitive": (dict(meshes__ground__primitive="plain"), "expected one of plane.*did you mean 'plane'"),
    "point light key on a directional light": (
        dict(lights__0__position=[0, 0, 1]),
        "lights\\[0\\].position: unknown key for a directional light \\('position' belongs to a point light; "
        "a directional light takes type, direction, intensity\\)"),
    "misspelt light key": (dict(lights__0__directon=[0, 0, 1]),
                           "did you mean 'direction'\\? a directional light takes type, direction, intensity"),
    "segments on a cube": (dict(meshes__ground={"primitive": "cube", "segments": 4, "material": "stone"}),
                           "meshes.ground.segments: does not apply to a cube"),
    "too few sphere segments": (dict(meshes__ground={"primitive": "sphere", "segments": [8, 1], "material": "stone"}),
                                "meshes.ground.segments: expected at least \\[3, 2\\] for a sphere, found \\[8, 1\\]"),
    "too few torus segments": (dict(meshes__ground={"primitive": "torus", "segments": 2, "material": "stone"}),
                               "expected at least \\[3, 3\\] for a torus, found \\[2, 2\\]"),
    "environment forward along up": (dict(lights=[{"type": "environment", "sky": {}, "forward": [0, 0, 2]}]),
                                     "lights\\[0\\].forward: is parallel to 'up'.*left edge \\(column 0\\)"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_scene_is_refused_at_validation(tmp_path, case):
    changes, pattern = BAD[case]
    with pytest.raises(BtforgeInputError, match=pattern) as info:
        validate(graph_with(tmp_path, with_changes(**changes)))
    assert "node 'img'" in str(info.value)       # located at the render node of the graph


def test_missing_file_hint_says_what_relative_paths_resolve_against(tmp_path):
    """A scene file's paths resolve against its own folder; an inline scene's against the graph's."""
    from btforge.plugins.render.loader import load_scene
    from btforge.stages import RunPaths
    (tmp_path / "scenes").mkdir()
    scene = with_changes(meshes={"ground": {"file": "quad.obj", "material": "stone"}})
    (tmp_path / "scenes" / "s.yaml").write_text(yaml.safe_dump(scene))
    paths = RunPaths(tmp_path, tmp_path)
    with pytest.raises(BtforgeInputError, match=r"scenes/quad.obj\n  hint: paths in a scene file are relative to "
                                                r"the scene file's folder"):
        load_scene("scenes/s.yaml", paths)
    with pytest.raises(BtforgeInputError, match=r"scene <inline>.*not found: .*\n  hint: paths in an inline scene "
                                                r"are relative to the graph file's folder"):
        load_scene(scene, paths)
    (tmp_path / "quad.obj").write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\n")
    assert load_scene(scene, paths).spec.meshes[0].file == str(tmp_path / "quad.obj")   # inline: from the graph


def test_mesh_without_uvs_where_a_texture_is_bound(tmp_path):
    (tmp_path / "bare.obj").write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n")
    scene = with_changes(meshes={"ground": {"file": "bare.obj", "material": "stone"}})
    with pytest.raises(BtforgeInputError, match="binds material 'stone' but its mesh file has no UV coordinates"):
        validate(graph_with(tmp_path, scene))
    scene = with_changes(meshes={"ground": {"file": "bare.obj", "color": [0.5, 0.5, 0.5]}})  # no texture: fine
    validate(graph_with(tmp_path, scene, wire=False))


def test_ply_vertex_uvs_are_read(tmp_path):
    ply = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
           "property float s\nproperty float t\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
           "-1 -1 0 0 0\n1 -1 0 1 0\n1 1 0 1 1\n-1 1 0 0 1\n3 0 1 2\n3 0 2 3\n")
    (tmp_path / "quad.ply").write_text(ply)
    validate(graph_with(tmp_path, with_changes(meshes={"ground": {"file": "quad.ply", "material": "stone"}})))


def test_material_bound_to_no_model_is_refused_at_validation(tmp_path):
    with pytest.raises(BtforgeInputError, match="input port 'stone' \\(ReflectanceModel\\) is not wired"):
        validate(graph_with(tmp_path, GOOD, wire=False))


def test_scene_read_feeds_render_through_scene_data(tmp_path):
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(GOOD))
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [16, 16], "lights": 8}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "material.stack"}},
        "scene": {"stage": "render.read_scene", "params": {"path": "scene.yaml"}},
        "a": {"stage": "render.image", "params": {"materials": ["stone"]},
              "inputs": {"scene_data": "scene.scene", "stone": "fit.model"}},
        "b": {"stage": "render.image", "params": {"scene": "scene.yaml"}, "inputs": {"stone": "fit.model"}},
    }}
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(graph))
    result = btforge.run(tmp_path / "g.yaml", only=["a", "b"], cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(result["a"]["image"].pixels, result["b"]["image"].pixels)
    scene = btforge.run(tmp_path / "g.yaml", only=["scene"], cache_dir=tmp_path / "cache")["scene"]["scene"]
    from btforge.buffers import Buffer
    (tmp_path / "s.npz").write_bytes(scene.to_bytes())
    again = Buffer.from_file(tmp_path / "s.npz", default_registry().types)
    assert again.content_key == scene.content_key and again.spec == scene.spec


# ----------------------------------------------------------------------------------------------- writing


def sweep_image(frames=3):
    from btforge.plugins.render.image import Image
    rng = np.random.default_rng(0)
    return Image(rng.uniform(0, 1, (frames, 6, 10, 3)).astype(np.float32), exposure=0.5, fps=8)


def test_image_write_formats(tmp_path):
    from btforge.context import StageContext
    from btforge.plugins.render.image import Image
    from btforge.plugins.stackio.images import read_exr
    from btforge.stages import RunPaths
    write = btforge.stage("render.write_image")
    ctx = StageContext("w", paths=RunPaths(tmp_path, tmp_path))
    single = Image(np.linspace(0, 2, 5 * 7 * 3, dtype=np.float32).reshape(5, 7, 3))
    write(ctx=ctx, image=single, path="one.exr")
    np.testing.assert_array_equal(read_exr(tmp_path / "one.exr"), single.pixels)   # linear, unchanged
    write(ctx=ctx, image=sweep_image(), path="sweep.png")
    assert sorted(p.name for p in tmp_path.glob("sweep_*.png")) == ["sweep_000.png", "sweep_001.png", "sweep_002.png"]
    write(ctx=ctx, image=sweep_image(), path="sweep.gif")
    import imageio.v3 as iio
    assert iio.imread(tmp_path / "sweep.gif").shape[:3] == (3, 6, 10)


def test_mp4_needs_a_video_plugin_known_at_validation(tmp_path):
    from btforge.plugins.render.image import mp4_backend
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(GOOD))
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [16, 16], "lights": 8}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "material.stack"}},
        "img": {"stage": "render.image", "params": {"scene": "scene.yaml"}, "inputs": {"stone": "fit.model"}},
        "mp4": {"stage": "render.write_image", "params": {"path": "out.mp4"}, "inputs": {"image": "img.image"}},
    }}
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(graph))
    if mp4_backend() is None:
        with pytest.raises(BtforgeInputError, match="MP4 needs an imageio video plugin"):
            validate(tmp_path / "g.yaml")
    else:
        btforge.run(tmp_path / "g.yaml", out_dir=tmp_path, cache_dir=tmp_path / "cache")
        assert (tmp_path / "out.mp4").stat().st_size > 0


def test_light_sweep_traces_once_and_turntable_traces_every_frame():
    from btforge.plugins.render.renderer import Counters, render
    from btforge.plugins.render.loader import load_scene
    from btforge.stages import RunPaths
    from test_render import constant_ptm, random_ptm
    scene = with_changes(animation={"type": "light_sweep", "frames": 4, "light": 0, "axis": [0, 0, 1]})
    counters = Counters()
    frames = render(load_scene(scene, RunPaths(Path.cwd(), Path.cwd())), {"stone": random_ptm(8, 8)}, counters)
    assert frames.shape == (4, 16, 16, 3)
    assert counters.passes["primary"]["rays"] == 16 * 16 and counters.passes["direct"]["evaluations"] == 4 * 16 * 16
    assert not np.allclose(frames[0], frames[1])
    scene = with_changes(animation={"type": "turntable", "frames": 3, "axis": [0, 1, 0], "degrees": 90})
    scene["meshes"]["ball"] = {"primitive": "cube", "size": 0.8, "position": [0, 0, 0.6]}
    counters = Counters()
    frames = render(load_scene(scene, RunPaths(Path.cwd(), Path.cwd())), {"stone": constant_ptm(0.5)}, counters)
    assert frames.shape == (3, 16, 16, 3) and counters.passes["primary"]["rays"] == 3 * 16 * 16
    assert not np.allclose(frames[0], frames[2])


def test_example_graphs_and_scenes_validate():
    graphs = Path(__file__).resolve().parents[1] / "graphs"
    from btforge.plugins.render.scene import parse_scene, read_scene_source
    from btforge.stages import RunPaths
    for scene in sorted((graphs / "scenes").glob("*.yaml")):
        data, source, base = read_scene_source(str(scene), RunPaths(graphs, graphs))
        assert parse_scene(data, source, base).materials
    check_graph(load_graph(graphs / "render_torus_environment.yaml"), default_registry())
    from btforge.plugins.render.bench import bench_scene
    for env in (False, True):
        parse_scene(bench_scene(env), "bench", Path.cwd())


def test_meshes_are_built_once_per_run_without_point_lights(tmp_path, monkeypatch):
    """The graph check and the scene check leave the meshes to the renderer, unless a point light needs them."""
    from btforge.plugins.render import geometry, loader, renderer
    built = []
    original = geometry.build_mesh

    def counted(spec, scene=None):
        built.append(spec.name)
        return original(spec, scene)
    for module in (geometry, loader, renderer):  # each holds its own name for it
        monkeypatch.setattr(module, "build_mesh", counted)
    btforge.run(graph_with(tmp_path, GOOD), cache_dir=None, out_dir=tmp_path)
    assert built == ["ground"]
    built.clear()
    validate(graph_with(tmp_path, with_changes(lights=[{"type": "point", "position": [0, 0, 1], "intensity": 1.0}])))
    assert built == ["ground"]  # the check that a point light is not inside a closed mesh needs the mesh
