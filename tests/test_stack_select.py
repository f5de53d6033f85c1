"""stack.select: views and lights by index or name; ptm.fit on a BTF points to it."""
import numpy as np
import pytest

import btforge
from btforge import BtforgeInputError
from btforge.runner import run


def _btf():
    return btforge.stage("demo.btf")(size=[6, 5], lights=7, views=3)["stack"]


def test_select_by_index_keeps_order_and_samples():
    stack = _btf()
    out = btforge.stage("stackio.select")(stack=stack, views=[2, 0], lights=[6, 1, 3])["stack"]
    assert out.samples.shape == (2, 3, 6, 5, 3)
    np.testing.assert_array_equal(out.samples[0, 1], stack.samples[2, 1])
    np.testing.assert_array_equal(out.samples[1, 0], stack.samples[0, 6])
    np.testing.assert_array_equal(out.lights, stack.lights[[6, 1, 3]])
    np.testing.assert_array_equal(out.views, stack.views[[2, 0]])


def test_select_by_angle_names_and_image_names():
    from btforge.plugins.stackio.select import angle_label
    stack = _btf()
    label_v = angle_label(stack.views[1], "view")
    label_l = angle_label(stack.lights[4], "light")
    out = btforge.stage("stackio.select")(stack=stack, views=[label_v], lights=[label_l])["stack"]
    np.testing.assert_array_equal(out.samples[0, 0], stack.samples[1, 4])
    named = btforge.stage("demo.material")(size=[4, 4], lights=8)["stack"]
    out = btforge.stage("stackio.select")(stack=named, lights=["light_005", 2])["stack"]
    assert out.names == ("light_005", "light_002")
    np.testing.assert_array_equal(out.samples[0, 0], named.samples[0, 5])


def test_empty_lists_keep_everything():
    stack = _btf()
    out = btforge.stage("stackio.select")(stack=stack)["stack"]
    np.testing.assert_array_equal(out.samples, stack.samples)


def test_bad_selections_are_reported_together():
    stack = _btf()
    with pytest.raises(BtforgeInputError) as info:
        btforge.stage("stackio.select")(stack=stack, lights=[9, "tl1_pl1", "nope"])
    text = str(info.value)
    assert "index 9 is out of range" in text and "'tl1_pl1'" in text and "'nope'" in text
    with pytest.raises(BtforgeInputError, match="twice"):
        btforge.stage("stackio.select")(stack=stack, views=[0, 0])
    with pytest.raises(BtforgeInputError, match="indices >= 0 or names"):
        btforge.stage("stackio.select")(stack=stack, views=[-1])


def test_bad_selection_is_refused_before_a_run(tmp_path):
    graph = {"nodes": {"btf": {"stage": "demo.btf", "params": {"size": [4, 4], "lights": 6, "views": 2}},
                       "pick": {"stage": "stackio.select", "params": {"views": 0}, "inputs": {"stack": "btf.stack"}}}}
    with pytest.raises(BtforgeInputError, match="expected a list of indices or names"):
        run(graph, out_dir=tmp_path)


def test_ptm_on_a_btf_points_to_stack_select_and_works_after_it(tmp_path):
    nodes = {"btf": {"stage": "demo.btf", "params": {"size": [4, 4], "lights": 8, "views": 2}},
             "fit": {"stage": "ptm.fit", "inputs": {"stack": "btf.stack"}}}
    with pytest.raises(BtforgeInputError, match="stackio.select"):
        run({"nodes": nodes}, out_dir=tmp_path)
    nodes["pick"] = {"stage": "stackio.select", "params": {"views": [1]}, "inputs": {"stack": "btf.stack"}}
    nodes["fit"]["inputs"] = {"stack": "pick.stack"}
    model = run({"nodes": nodes}, out_dir=tmp_path)["fit"]["model"]
    assert model.coeffs.shape == (4, 4, 3, 6)


def _check(tmp_path, nodes):
    import yaml

    from btforge.graph import check_graph, load_graph
    from btforge.registry import default_registry
    graph = tmp_path / "g.yaml"
    graph.write_text(yaml.safe_dump({"nodes": nodes}))
    return check_graph(load_graph(graph), default_registry(), tmp_path)


@pytest.mark.parametrize("source", ["lvp", "store", "btf", "capture"])
def test_a_btf_wired_into_a_single_view_fit_is_caught_at_validation(tmp_path, source):
    from btforge.plugins.stackio.images import write_stack
    from ubo2014_files import random_factors, write_dfmf
    if source in ("lvp", "capture"):
        write_stack(_btf(), tmp_path / "cap", fmt="png")
        path = str(tmp_path / "cap" / "lights.lvp")
    elif source == "store":
        path = str(tmp_path / "s.zarr")
        run({"nodes": {"btf": {"stage": "demo.btf", "params": {"size": [6, 5], "lights": 7, "views": 3,
                                                               "store": path}}}}, out_dir=tmp_path)
    else:
        path = str(tmp_path / "m.btf")
        write_dfmf(tmp_path / "m.btf", np.radians([[10, 0], [40, 90], [60, 200]]), np.radians([[0, 0], [30, 0], [50, 90]]),
                   4, 3, random_factors(np.random.default_rng(0), 9, 12))
    if source == "capture":
        nodes = {"fit": {"stage": "ptm.fit_capture", "params": {"path": path}}}
        with pytest.raises(BtforgeInputError, match="expected a single-view capture.*found 3 views"):
            _check(tmp_path, nodes)
        return
    nodes = {"read": {"stage": "stackio.read", "params": {"path": path}},
             "fit": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}}}
    with pytest.raises(BtforgeInputError) as caught:
        _check(tmp_path, nodes)
    text = caught.value.render()
    assert "node 'fit', input 'stack': ptm.fit expects views: 1, found 3 in 'read.stack'" in text
    assert path in text and "inputs: {stack: read.stack}" in text  # the hint names the port to re-wire
    nodes["pick"] = {"stage": "stackio.select", "params": {"views": [0, 2]}, "inputs": {"stack": "read.stack"}}
    nodes["fit"]["inputs"] = {"stack": "pick.stack"}
    with pytest.raises(BtforgeInputError, match="found 2 in 'pick.stack'"):
        _check(tmp_path, nodes)
    nodes["pick"]["params"]["views"] = [2]
    _check(tmp_path, nodes)


def test_view_counts_pass_through_stages_that_keep_them(tmp_path):
    btf = {"stage": "demo.btf", "params": {"size": [6, 5], "lights": 7, "views": 3}}
    fit = {"stage": "ptm.fit", "inputs": {"stack": "last.stack"}}
    for chain in ([{"stage": "normalize.stack"}], [{"stage": "stackio.select", "params": {"lights": [0, 2, 4, 6]}}],
                  [{"stage": "synth.crop", "params": {"size": [4, 4]}, "port": "input", "out": "output"},
                   {"stage": "normalize.stack"}]):
        nodes, upstream = {"btf": btf}, "btf.stack"
        for i, step in enumerate(chain):
            name = "last" if i == len(chain) - 1 else f"step{i}"
            port, out = step.get("port", "stack"), step.get("out", "stack")
            nodes[name] = {"stage": step["stage"], "params": step.get("params", {}), "inputs": {port: upstream}}
            upstream = f"{name}.{out}"
        nodes["fit"] = {"stage": "ptm.fit", "inputs": {"stack": upstream}}
        with pytest.raises(BtforgeInputError, match=r"ptm.fit expects views: 1, found 3 in '.*' \(from param 'views'\)"):
            _check(tmp_path, nodes)
    nodes = {"btf": btf, "pick": {"stage": "stackio.select", "params": {"views": [1]}, "inputs": {"stack": "btf.stack"}},
             "last": {"stage": "normalize.stack", "inputs": {"stack": "pick.stack"}}, "fit": fit}
    _check(tmp_path, nodes)  # the selection's own count (1) wins over its input's, and passes on

