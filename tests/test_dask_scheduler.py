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
        "top": {"stage": "stack.select", "params": {"views": [0]}, "inputs": {"stack": "btf.stack"}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "top.stack"}},
        "lafortune": {"stage": "lafortune.fit", "params": {"lobes": 1}, "inputs": {"stack": "btf.stack"}}}}
    local = cluster_run(graph, out_dir=tmp_path, use_cache=False)
    distributed = cluster_run(graph, out_dir=tmp_path, use_cache=False, scheduler="dask")
    a, b = local["sh"]["model"], distributed["sh"]["model"]
    assert b.coeffs.shape == a.coeffs.shape == (20, 9, 3, 4, 9)
    np.testing.assert_allclose(b.coeffs, a.coeffs, rtol=1e-5, atol=1e-5)
    notes = {r.node: r.notes for r in distributed.report}
    assert notes["sh"]["scheduler"] == "dask" and notes["sh"]["workers"] == 2
    assert notes["sh"]["bands"] == 5 and notes["sh"]["tasks"] > notes["sh"]["bands"]
    assert notes["sh"]["bytes_to_client"] >= a.coeffs.nbytes
    # the store's lights reach every band bit for bit, so the non-linear fit lands in the same minimum; float32
    # sums over bands of another size still differ in the last bits, which LM carries to ~1e-5 in a few texels
    assert notes["lafortune"]["scheduler"] == "dask"
    for field in LafortuneModel.texel_fields:
        np.testing.assert_allclose(getattr(distributed["lafortune"]["model"], field),
                                   getattr(local["lafortune"]["model"], field), rtol=1e-4, atol=1e-4)
    # the selected view is an in-memory stack: ptm.fit runs in this process, and equals the local run
    assert "scheduler" not in notes["ptm"]
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
