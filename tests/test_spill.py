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
