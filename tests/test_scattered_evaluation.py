"""Every representation can be evaluated texel by texel at per-texel lights and views (what a renderer needs),
and that agrees with evaluating the whole model at one light and view."""
import numpy as np
import pytest

import btforge
from btforge import BtforgeInputError


def models():
    btf = btforge.stage("demo.btf")(size=[6, 7], lights=16, views=4)["stack"]
    top = btforge.stage("demo.material")(size=[6, 7], lights=16)["stack"]
    return {
        "ptm": btforge.stage("ptm.fit")(stack=top, variant="lrgb")["model"],
        "sh": btforge.stage("sh.fit")(stack=btf, light_order=3, view_order=2)["model"],
        "sh-quantized": btforge.stage("sh.fit")(stack=btf, light_order=3, view_order=2, quantize=True)["model"],
        "lafortune-lum": btforge.stage("lafortune.fit")(stack=btf, lobes=1)["model"],
        "lafortune-rgb": btforge.stage("lafortune.fit")(stack=btf, lobes=2, variant="rgb")["model"],
    }


MODELS = models()


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("light,view", [([0.3, 0.2, 0.93], [0, 0, 1]), ([0.9, 0.0, 0.1], [0.5, 0.1, 0.86]),
                                        ([0.0, 0.0, 1.0], [-0.7, 0.0, 0.714])])
def test_scattered_equals_whole_model(name, light, view):
    model = MODELS[name]
    light = np.array(light) / np.linalg.norm(light)
    view = np.array(view) / np.linalg.norm(view)
    rows, cols = np.meshgrid(np.arange(model.height), np.arange(model.width), indexing="ij")
    n = rows.size
    views = np.tile(view, (n, 1)) if model.view_dependent else None
    scattered = model.evaluate_texels(rows.ravel(), cols.ravel(), np.tile(light, (n, 1)), views)
    whole = model.evaluate(light[None], view[None] if model.view_dependent else None)[0, 0]
    np.testing.assert_allclose(scattered.reshape(whole.shape), whole, rtol=2e-4, atol=2e-5)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_bad_lookups_are_refused(name):
    model = MODELS[name]
    with pytest.raises(BtforgeInputError, match="inside the"):
        model.evaluate_texels(np.array([model.height]), np.array([0]), np.array([[0, 0, 1.0]]))
    with pytest.raises(BtforgeInputError, match=r"lights \[N, 3\]"):
        model.evaluate_texels(np.array([0, 1]), np.array([0, 1]), np.array([[0, 0, 1.0]]))


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_representation_renders_like_relight_on_the_plane(name):
    from test_render import draw, plane_scene
    model = MODELS[name]
    light = np.array([[-0.4, 0.5, 0.7]]) / np.linalg.norm([-0.4, 0.5, 0.7])
    image, _ = draw(plane_scene(model.width, model.height,
                                lights=[{"type": "directional", "direction": light[0].tolist(), "intensity": 1.0}]),
                    {"stone": model})
    np.testing.assert_allclose(image, model.evaluate(light)[0, 0], rtol=2e-4, atol=2e-5)
