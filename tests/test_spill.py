"""Spilled arrays: results kept in a file whose pages are handed back, checked, hashed and written page by page."""
import io

import numpy as np
import pytest

from btforge.buffers import Buffer, SampleStack
from btforge.spill import finite_range, is_spilled, pages, release, spilled_empty, write_npy


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def test_a_spilled_array_keeps_its_data_without_staying_resident():
    big = spilled_empty((96, 1 << 18), np.float32)  # 96 MB
    assert is_spilled(big) and is_spilled(big[3:5]) and not is_spilled(np.zeros(3))
    before = _resident_mb()
    for row in range(big.shape[0]):
        big[row] = row
        release(big[row])
    grown = _resident_mb() - before
    total = sum(float(part.sum(dtype=np.float64)) for part in pages(big, 8 << 20))
    assert total == sum(range(96)) * (1 << 18)
    assert max(grown, _resident_mb() - before) < 48  # written and read back, never all resident at once
    np.testing.assert_array_equal(big[:, 7], np.arange(96, dtype=np.float32))


def test_release_never_loses_data_of_other_arrays(tmp_path):
    ordinary = np.arange(10.0)
    release(ordinary)
    np.testing.assert_array_equal(ordinary, np.arange(10.0))
    path = tmp_path / "a.bin"
    np.arange(4096, dtype=np.float64).tofile(path)
    private = np.memmap(path, np.float64, "c", 0, (4096,))
    private[:] = -1.0            # copy-on-write: only this map sees it, so it must not be dropped
    release(private)
    assert (private == -1.0).all()


@pytest.mark.parametrize("array", [
    np.arange(24, dtype=np.float32).reshape(2, 3, 4), np.asfortranarray(np.arange(12.0).reshape(3, 4)),
    np.arange(10, dtype=np.int16)[::3], np.zeros((0, 5), np.uint8), np.array(3.5), np.ones(7, np.float16)],
    ids=["c", "fortran", "strided", "empty", "scalar", "half"])
def test_write_npy_writes_what_np_save_writes(array):
    ours, theirs = io.BytesIO(), io.BytesIO()
    write_npy(ours, array)
    np.save(theirs, array, allow_pickle=False)
    assert ours.getvalue() == theirs.getvalue()


def test_a_spilled_buffer_round_trips_and_hashes_like_its_copy():
    rng = np.random.default_rng(0)
    samples = spilled_empty((2, 3, 5, 4, 3), np.float32)
    samples[:] = rng.random(samples.shape, dtype=np.float32)
    lights, views = [[0, 0, 1], [0.5, 0, 0.8], [0, 0.5, 0.8]], [[0, 0, 1], [0.3, 0, 0.9]]
    spilled = SampleStack(samples, lights, views)
    copy = SampleStack(np.array(samples), lights, views)
    assert spilled.content_key == copy.content_key
    handle = io.BytesIO()
    spilled.write_npz(handle)
    handle.seek(0)
    back = Buffer.from_file(handle, {"SampleStack": SampleStack})
    np.testing.assert_array_equal(back.samples, copy.samples)
    assert finite_range(samples)
    samples_bad = np.array(samples)
    samples_bad[1, 2, 3] = np.nan
    assert not finite_range(samples_bad)


def _spill_target(array: np.ndarray) -> str:
    """Where a spilled array's file lives: ``/memfd:...`` for a memory file, else its (deleted) path."""
    import os

    from btforge import spill
    return os.readlink(f"/proc/self/fd/{spill._files[id(array.base)].fileno()}")


@pytest.mark.parametrize("share", [0.25, 0.0], ids=["memory file", "disk file"])
def test_spills_stay_in_memory_files_up_to_their_share_then_go_to_the_cache_root(monkeypatch, share):
    import gc
    import os

    from btforge import spill
    from btforge.locations import default_cache_root
    monkeypatch.setattr(spill, "MEMORY_FILE_SHARE", share)
    before = spill._memory_file_bytes[0]
    big = spilled_empty((64, 1 << 14), np.float32)  # 4 MB
    target = _spill_target(big)
    if share and hasattr(os, "memfd_create") and spill._available_memory_bytes() > 4 * big.nbytes:
        assert target.startswith("/memfd:") and spill._memory_file_bytes[0] == before + big.nbytes
    else:
        assert target.startswith(str(default_cache_root())) and spill._memory_file_bytes[0] == before
    for row in range(big.shape[0]):
        big[row] = row
        release(big[row])
    np.testing.assert_array_equal(big[:, 5], np.arange(64, dtype=np.float32))
    del big
    gc.collect()
    assert spill._memory_file_bytes[0] == before  # a freed spill gives its share back


def test_blocks_read_into_one_reused_buffer_equal_fresh_blocks():
    from btforge.spill import read_block, write_items
    data = np.arange(5 * 9 * 4 * 3, dtype=np.float32).reshape(5, 9, 4, 3)
    spilled = spilled_empty(data.shape, np.float32)
    write_items(spilled, 0, data)
    buffer = np.empty(5 * 4 * 4 * 3, np.float32)
    for array in (spilled, data, np.asfortranarray(data)):
        for start in range(0, 9, 4):  # bands of 4, 4 and 1 rows along axis 1
            block = read_block(array, 1, slice(start, start + 4), buffer)
            assert np.shares_memory(block, buffer)
            np.testing.assert_array_equal(block, data[:, start:start + 4])
    with pytest.raises(ValueError, match="cannot take a block"):
        read_block(spilled, 1, slice(0, 5), buffer)  # 5 rows do not fit a buffer of 4
    with pytest.raises(ValueError, match="cannot take a block"):
        read_block(spilled, 1, slice(0, 2), buffer.astype(np.float64))
