"""--scheduler dask: per-texel stages on a stored stack as dask tasks on a 2-worker LocalCluster (loopback)."""
import numpy as np
import pytest

import btforge
from btforge import BtforgeInputError
from btforge.plugins.lafortune.model import LafortuneModel

pytest.importorskip("dask.distributed")


@pytest.fixture(scope="module")
def cluster_run():
    from btforge.scheduler import close_clients
    yield btforge.run
    close_clients()


def test_dask_run_equals_the_single_process_run(tmp_path, cluster_run, monkeypatch):
    import btforge.scheduler
    monkeypatch.setattr(btforge.scheduler, "BAND_BYTES", 4 * 12 * 9 * 3 * 4 * 4)  # 4 rows a band: 5 tasks to join
    graph = {"nodes": {
        "btf": {"stage": "demo.btf", "params": {"size": [20, 9], "lights": 12, "views": 4, "block": [4, 9],
                                                "store": str(tmp_path / "b.zarr")}},
        "sh": {"stage": "sh.fit", "params": {"light_order": 3, "view_order": 2, "space": "srgb", "smoothness": 0},
               "inputs": {"stack": "btf.stack"}},  # auto would judge its settings on all texels: not per band
        "top": {"stage": "stackio.select", "params": {"views": [0]}, "inputs": {"stack": "btf.stack"}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "top.stack"}},
        "lafortune": {"stage": "lafortune.fit", "params": {"lobes": 1}, "inputs": {"stack": "btf.stack"}}}}
    local = cluster_run(graph, out_dir=tmp_path, use_cache=False)
    distributed = cluster_run(graph, out_dir=tmp_path, use_cache=False, scheduler="dask")
    a, b = local["sh"]["model"], distributed["sh"]["model"]
    assert b.coeffs.shape == a.coeffs.shape == (20, 9, 3, 4, 9)
    np.testing.assert_allclose(b.coeffs, a.coeffs, rtol=1e-5, atol=1e-5)
    notes = {r.node: r.notes for r in distributed.report}
    assert notes["sh"]["scheduler"] == "dask" and notes["sh"]["workers"] == 2
    assert notes["sh"]["bands"] == notes["sh"]["tasks"] == 5
    placement = {r.node: r.placement for r in distributed.report}
    assert placement["sh"] == {"where": "dask", "tasks": 5, "workers": 2}
    assert notes["sh"]["bytes_to_client"] >= a.coeffs.nbytes
    # the store's lights reach every band bit for bit, so the non-linear fit lands in the same minimum; float32
    # sums over bands of another size still differ in the last bits, which LM carries to ~1e-5 in a few texels
    assert notes["lafortune"]["scheduler"] == "dask"
    for field in LafortuneModel.texel_fields:
        np.testing.assert_allclose(getattr(distributed["lafortune"]["model"], field),
                                   getattr(local["lafortune"]["model"], field), rtol=1e-4, atol=1e-4)
    # the selected view is an in-memory stack: ptm.fit runs in this process, says so, and equals the local run
    assert "scheduler" not in notes["ptm"] and placement["ptm"] == {"where": "local"}
    assert any("runs in this process, not on dask" in w and "held whole" in w for w in notes["ptm"]["warnings"])
    np.testing.assert_array_equal(distributed["ptm"]["model"].coeffs, local["ptm"]["model"].coeffs)


def test_unknown_scheduler_is_a_clear_error(tmp_path):
    with pytest.raises(BtforgeInputError, match="local, dask or tcp://HOST:PORT"):
        btforge.run({"nodes": {"m": {"stage": "demo.material"}}}, out_dir=tmp_path, scheduler="dusk")


def test_unreachable_scheduler_is_a_clear_error(tmp_path, monkeypatch):
    import btforge.scheduler
    monkeypatch.setattr(btforge.scheduler, "_clients", {})

    def refuse(address, timeout):
        raise OSError(f"Timed out trying to connect to {address}")
    import dask.distributed
    monkeypatch.setattr(dask.distributed, "Client", refuse)
    with pytest.raises(BtforgeInputError, match="cannot reach the dask scheduler") as info:
        btforge.scheduler.client_for("tcp://127.0.0.1:9")
    assert "dask worker tcp://127.0.0.1:9 --nthreads 1" in info.value.hint


@pytest.fixture(scope="module")
def loopback_scheduler():
    """A 2-worker LocalCluster on loopback, reached by address as ``--scheduler tcp://HOST:PORT`` is."""
    from dask.distributed import LocalCluster

    from btforge.scheduler import close_clients
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None)
    yield cluster.scheduler_address
    close_clients()
    cluster.close()


def test_default_fits_of_a_store_run_on_the_cluster(tmp_path, loopback_scheduler, monkeypatch):
    """At default params (space: auto) every per-texel fit of a store runs on the workers: auto is decided once
    on a grid of texels, then the bands are fitted with that space; a fit that cannot be split warns why."""
    import btforge.scheduler
    monkeypatch.setattr(btforge.scheduler, "BAND_BYTES", 6 * 20 * 14 * 3 * 4)  # 6 rows a band: 3 tasks
    graph = {"nodes": {
        "btf": {"stage": "demo.btf", "params": {"size": [16, 14], "lights": 20, "views": 1, "block": [6, 14],
                                                "store": str(tmp_path / "top.zarr")}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "btf.stack"}},
        "sh": {"stage": "sh.fit", "inputs": {"stack": "btf.stack"}},
        "quantized": {"stage": "sh.fit", "params": {"quantize": True}, "inputs": {"stack": "btf.stack"}}}}
    local = btforge.run(graph, out_dir=tmp_path, use_cache=False)
    remote = btforge.run(graph, out_dir=tmp_path, use_cache=False, scheduler=loopback_scheduler)
    placement = {r.node: r.placement for r in remote.report}
    notes = {r.node: r.notes for r in remote.report}
    for node in ("ptm", "sh"):
        assert placement[node] == {"where": loopback_scheduler, "tasks": 3, "workers": 2}
        assert notes[node]["space"] == {r.node: r.notes for r in local.report}[node]["space"]
        # each texel's fit reads the same bytes with the same float32 operations; only the grouping of texels
        # into launches differs, so values of order 1 agree to a few float32 roundings
        a, b = remote[node]["model"].coeffs, local[node]["model"].coeffs
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * max(1.0, float(np.abs(b).max())))
    assert placement["quantized"] == {"where": "local"}
    assert any("node" not in w and "quantize: True" in w and f"not on {loopback_scheduler}" in w
               for w in notes["quantized"]["warnings"])
    np.testing.assert_array_equal(remote["quantized"]["model"].coeffs, local["quantized"]["model"].coeffs)


def test_a_streamed_capture_is_fitted_on_the_cluster(tmp_path, loopback_scheduler, monkeypatch):
    """stack.read of images with only per-texel readers streams; on a cluster each band's samples are sent from
    this process to the workers, and the result equals the local run's."""
    import btforge.plugins.stackio.images
    import btforge.scheduler
    monkeypatch.setattr(btforge.plugins.stackio.images, "STREAM_MIN_BYTES", 0)  # stream even this tiny capture
    btforge.run({"nodes": {
        "m": {"stage": "demo.material", "params": {"size": [18, 12], "lights": 16, "bumps": 4}},
        "w": {"stage": "stackio.write", "params": {"dir": "cap", "format": "png"}, "inputs": {"stack": "m.stack"}}}},
        out_dir=tmp_path, use_cache=False)
    monkeypatch.setattr(btforge.scheduler, "BAND_BYTES", 8 * 16 * 12 * 3 * 4)  # 8 rows a band: 3 tasks
    graph = {"nodes": {
        "read": {"stage": "stackio.read", "params": {"path": str(next((tmp_path / "cap").glob("*.lp")))}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}}}}
    local = btforge.run(graph, out_dir=tmp_path, use_cache=False)
    remote = btforge.run(graph, out_dir=tmp_path, use_cache=False, scheduler=loopback_scheduler)
    nodes = {r.node: r for r in remote.report}
    assert nodes["read"].notes["streamed"] is True
    assert nodes["ptm"].placement == {"where": loopback_scheduler, "tasks": 3, "workers": 2}
    # the same bytes per texel and the same float32 operations: a few roundings of coefficients of order 1
    np.testing.assert_allclose(remote["ptm"]["model"].coeffs, local["ptm"]["model"].coeffs, rtol=0, atol=1e-5)


def test_a_fit_left_at_auto_for_a_ptm_file_fits_srgb_on_the_cluster(tmp_path, loopback_scheduler, monkeypatch):
    """The graph check narrows ``space: auto`` before anything runs: the bands sent to the workers fit display
    values, as the .ptm file holds, on a rendered capture where ``auto`` alone picks linear."""
    import btforge.plugins.stackio.images
    import btforge.scheduler
    from btforge.plugins.ptm.bench import make_synthetic_capture
    monkeypatch.setattr(btforge.plugins.stackio.images, "STREAM_MIN_BYTES", 0)  # stream even this tiny capture
    monkeypatch.setattr(btforge.scheduler, "BAND_BYTES", 12 * 38 * 32 * 3 * 4)  # 12 rows a band: 3 tasks
    (tmp_path / "cap").mkdir()
    lp = make_synthetic_capture(tmp_path / "cap", 32, 38)
    graph = {"nodes": {
        "read": {"stage": "stackio.read", "params": {"path": str(lp)}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}},
        "write": {"stage": "ptm.write", "params": {"path": "m.ptm"}, "inputs": {"model": "ptm.model"}}}}
    remote = btforge.run(graph, out_dir=tmp_path, use_cache=False, scheduler=loopback_scheduler, only=["ptm", "write"])
    alone = btforge.run({"nodes": {n: graph["nodes"][n] for n in ("read", "ptm")}}, out_dir=tmp_path, use_cache=False)
    assert alone["ptm"]["model"].space == "linear"  # what auto picks when no writer constrains it
    nodes = {r.node: r for r in remote.report}
    assert nodes["ptm"].placement == {"where": loopback_scheduler, "tasks": 3, "workers": 2}
    assert remote["ptm"]["model"].space == nodes["ptm"].notes["space"] == "srgb"
    assert "ptm.write" in nodes["ptm"].notes["space (auto)"] and (tmp_path / "m.ptm").stat().st_size > 0
