"""Ray fields survive a trip to disk, and the disk cache keeps, finds and trims them."""

import os
import sys
import threading
import time

import numpy as np
import pytest

from fixtures.rigs import two_camera_rig
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import Settings, field_key, prepare
from multiscale_camera.io.cache import IN_USE_SECONDS, FieldCache
from multiscale_camera.io.fields import field_from_arrays, field_to_arrays

SETTINGS = Settings(2.0, 48**3)


def all_rays(fld):
    w, h = fld.rig.size
    iy, ix = np.mgrid[0:h, 0:w]
    return fld.rays(ix.ravel(), iy.ravel()), fld.exit_index(ix.ravel(), iy.ravel())


@pytest.fixture(scope="module")
def rig():
    cams, masks = two_camera_rig(40, 30)
    return Rig(cams, masks)


@pytest.mark.parametrize("method", ["SCALAR_FIELD", "IMAGE_BLEND", "LINEAR"])
def test_round_trip_through_npz_hands_out_identical_rays(rig, method, tmp_path):
    fld = prepare(rig, method, SETTINGS)
    path = tmp_path / "f.npz"
    np.savez(path, **field_to_arrays(fld))
    with np.load(path, allow_pickle=False) as data:
        back = field_from_arrays({k: data[k] for k in data.files}, rig)
    assert type(back) is type(fld) and back.method == fld.method
    assert back.warnings == fld.warnings and back.grids == fld.grids
    assert back.stats == fld.stats and back.solver == fld.solver
    a, ea = all_rays(fld)
    b, eb = all_rays(back)
    for name in ("vertices", "membership", "pixels", "start_depth", "reach"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    if ea is None:
        assert eb is None
    else:
        np.testing.assert_array_equal(ea, eb)


def test_a_nested_field_survives_the_disk_cache(rig, tmp_path):
    """A field on nested grids holds a step function and the levels' membership, which
    the npz cannot (and rays do not) need: its rays come back identical."""
    from dataclasses import replace

    fld = prepare(rig, "SCALAR_FIELD", replace(SETTINGS, nested=True))
    assert fld.domain is not None and fld.traced.step is None
    path = tmp_path / "f.npz"
    np.savez(path, **field_to_arrays(fld))
    with np.load(path, allow_pickle=False) as data:
        back = field_from_arrays({k: data[k] for k in data.files}, rig)
    assert back.traced.step is None and back.domain is None
    np.testing.assert_array_equal(all_rays(fld)[0].vertices, all_rays(back)[0].vertices)


def test_unknown_version_is_refused(rig):
    arrays = field_to_arrays(prepare(rig, "IMAGE_BLEND", SETTINGS))
    arrays["meta"] = np.frombuffer(b'{"version": 99, "class": "x", "plain": {}}', np.uint8)
    with pytest.raises(ValueError, match="field arrays of version 99, not 1"):
        field_from_arrays(arrays, rig)


def test_disk_cache_hit_after_restart_miss_after_change_and_trim(rig, tmp_path):
    key = field_key(rig, "IMAGE_BLEND", SETTINGS)
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    cache = FieldCache(str(tmp_path))
    assert cache.get(key, rig) is None and cache.misses == 1
    assert cache.put(key, fld) is None
    assert os.path.isfile(tmp_path / f"{key}.npz")
    # a fresh cache (another Blender session) reads it from disk
    again = FieldCache(str(tmp_path))
    got = again.get(key, rig)
    assert got is not None and (again.hits, again.disk_hits, again.misses) == (1, 1, 0)
    np.testing.assert_array_equal(got.weights, fld.weights)
    assert again.get(key, rig) is got and again.disk_hits == 1  # then from memory
    # another mask: another key, a miss
    masks = rig.masks.copy()
    masks[1, 10, 10] = not masks[1, 10, 10]
    other = Rig(rig.cameras, masks)
    assert field_key(other, "IMAGE_BLEND", SETTINGS) != key
    assert again.get(field_key(other, "IMAGE_BLEND", SETTINGS), other) is None
    # size limit: the oldest entry goes first, the newest always stays
    size = os.path.getsize(tmp_path / f"{key}.npz")
    again.put("b" * 40, fld)
    os.utime(tmp_path / f"{key}.npz", (1, 1))
    again.limit_mb = 1.5 * size / (1 << 20)
    assert again.trim() == 1
    assert sorted(os.listdir(tmp_path)) == ["b" * 40 + ".npz"]
    assert again.clear() == 1 and os.listdir(tmp_path) == [] and again.memory == {}


def test_a_damaged_entry_is_a_miss_and_is_removed(rig, tmp_path):
    key = field_key(rig, "IMAGE_BLEND", SETTINGS)
    (tmp_path / f"{key}.npz").write_bytes(b"not a zip")
    cache = FieldCache(str(tmp_path))
    assert cache.get(key, rig) is None and cache.misses == 1
    assert not (tmp_path / f"{key}.npz").exists()


def test_put_creates_a_missing_cache_folder(rig, tmp_path):
    folder = tmp_path / "not" / "there"
    cache = FieldCache(str(folder))
    assert cache.put("k" * 40, prepare(rig, "IMAGE_BLEND", SETTINGS)) is None
    assert (folder / ("k" * 40 + ".npz")).is_file()


def test_the_build_report_travels_with_the_field(rig):
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    assert not hasattr(field_from_arrays(field_to_arrays(fld), rig), "report")
    fld.report = {"version": 1, "folds": 3, "cameras": [{"name": "C1"}]}
    back = field_from_arrays(field_to_arrays(fld), rig)
    assert back.report == fld.report


def test_an_unwritable_cache_says_so_and_keeps_the_field_in_memory(rig, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    cache = FieldCache(str(blocker))
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    said = cache.put("k" * 40, fld)
    assert said.startswith("The field cache could not be written (")
    assert said.endswith("); builds are not kept on disk")
    assert cache.get("k" * 40, rig) is fld


def test_voxel_budget_capping_the_accuracy_target_is_explained(rig):
    import re

    fld = prepare(rig, "SCALAR_FIELD", Settings(0.05, 24**3))
    pattern = (
        r"The accuracy target of 0\.05 px wants [0-9.e-]+-unit cells; the voxel budget allows "
        r"[0-9.e-]+: transitions near the smallest camera may be coarser than asked \(raise "
        r"the quality, or move that camera's near plane farther from its eye\)"
    )
    assert any(re.fullmatch(pattern, w) for w in fld.warnings), fld.warnings


def test_trim_leaves_fields_in_use(rig, tmp_path):
    """Fields read or written in the last IN_USE_SECONDS stay past the size limit: on a
    farm's shared folder another worker may be about to read them."""
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    cache = FieldCache(str(tmp_path), limit_mb=1e-6)
    cache.put("a" * 40, fld)
    cache.put("b" * 40, fld)
    assert len(os.listdir(tmp_path)) == 2  # both written just now: both in use
    old = time.time() - IN_USE_SECONDS - 1
    os.utime(tmp_path / ("a" * 40 + ".npz"), (old, old))
    assert cache.trim() == 1
    assert os.listdir(tmp_path) == ["b" * 40 + ".npz"]


DAMAGED = "The cached field '{}.npz' was damaged ({}): it was deleted and the field is built again"


def test_damaged_entry_that_loads_fails_its_checksum_is_deleted_and_said(rig, tmp_path):
    key = field_key(rig, "IMAGE_BLEND", SETTINGS)
    cache = FieldCache(str(tmp_path))
    cache.put(key, prepare(rig, "IMAGE_BLEND", SETTINGS))
    path = tmp_path / f"{key}.npz"
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["array.weights"] = arrays["array.weights"][::-1].copy()  # loads, yet wrong
    np.savez(path, **arrays)
    fresh = FieldCache(str(tmp_path))
    assert fresh.get(key, rig) is None and fresh.misses == 1
    assert not path.exists()
    assert fresh.take_notices() == [DAMAGED.format(key, "its arrays do not match their checksum")]
    assert fresh.take_notices() == []  # said once


def test_entry_without_checksum_is_deleted_and_said(rig, tmp_path):
    key = field_key(rig, "IMAGE_BLEND", SETTINGS)
    np.savez(tmp_path / f"{key}.npz", **field_to_arrays(prepare(rig, "IMAGE_BLEND", SETTINGS)))
    cache = FieldCache(str(tmp_path))
    assert cache.get(key, rig) is None
    assert cache.take_notices() == [DAMAGED.format(key, "it has no checksum")]


def test_cache_folder_that_is_a_file_falls_back_to_memory_with_a_message(
    rig, tmp_path, monkeypatch
):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("MULTISCALE_CACHE_DIR", str(blocker))
    cache = FieldCache(lazy_folder=True)
    assert cache.folder is None
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    assert cache.put("k" * 40, fld) is None and cache.get("k" * 40, rig) is fld
    assert cache.take_notices() == [
        f"The field cache folder '{blocker}' cannot be used (File exists): fields are kept "
        "in memory only, for this session; point $MULTISCALE_CACHE_DIR at a writable folder "
        "to keep them on disk"
    ]


def _write_many(folder, times):
    """Worker of the test below: put the same field under one key ``times`` times."""
    cams, masks = two_camera_rig(40, 30)
    rig = Rig(cams, masks)
    cache = FieldCache(folder)
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    for _ in range(times):
        assert cache.put("shared" * 7, fld) is None


def test_two_processes_writing_one_entry_leave_a_whole_one(rig, tmp_path):
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    writers = [ctx.Process(target=_write_many, args=(str(tmp_path), 15)) for _ in range(2)]
    for w in writers:
        w.start()
    reader = FieldCache(str(tmp_path))
    reads = 0
    while any(w.is_alive() for w in writers):
        reader.memory.clear()
        reads += reader.get("shared" * 7, rig) is not None
    for w in writers:
        w.join()
        assert w.exitcode == 0
    reader.memory.clear()
    assert reader.get("shared" * 7, rig) is not None
    assert reader.take_notices() == []  # no reader ever saw part of an entry
    assert sorted(os.listdir(tmp_path)) == ["shared" * 7 + ".npz"]  # no temporary left


def test_memory_reads_during_a_concurrent_trim_raise_no_key_error():
    """The live picture's thread reads the cache while the main thread stores: a read
    that moved an entry to the end (``pop`` then set) raced the trim to KeyError."""
    cache = FieldCache(folder=None)
    errors = []
    stop = threading.Event()

    def reader():
        try:
            while not stop.is_set():
                for key in ("a", "b", "c"):
                    cache.get(key, None)
        except Exception as err:  # the race this test is about
            errors.append(err)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=reader) for _ in range(3)]
        for t in threads:
            t.start()
        for i in range(20000):
            cache._remember("abc"[i % 3], i)
        stop.set()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(switch)
    assert errors == []
    assert len(cache.memory) <= 2


def test_cache_limit_counts_megabytes_of_2_20_bytes_as_the_memory_budget(rig, tmp_path):
    """The cache limit's MB are Blender's (2**20 bytes), as the Memory Budget's and
    ``size_text``'s: a limit of exactly the entries' size in those MB keeps them all
    (counted in MB of 10**6 bytes it fell 5% short and removed one)."""
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    cache = FieldCache(str(tmp_path))
    cache.put("a" * 40, fld)
    cache.put("b" * 40, fld)
    old = time.time() - IN_USE_SECONDS - 1
    os.utime(tmp_path / ("a" * 40 + ".npz"), (old, old))
    os.utime(tmp_path / ("b" * 40 + ".npz"), (old + 1, old + 1))
    total = cache.size_bytes()
    assert cache.trim(limit_mb=total / 2**20) == 0
    assert len(os.listdir(tmp_path)) == 2
    assert cache.trim(limit_mb=(total - 1) / 2**20) == 1  # a byte over: the oldest goes
    assert os.listdir(tmp_path) == ["b" * 40 + ".npz"]


def test_clear_forgets_the_default_folder_while_a_scene_folder_is_in_use(rig, tmp_path):
    """Clear Cache after a scene with its own cache folder cleared that folder alone: the
    next scene, on the default folder, still found the field it had built before."""
    fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    cache = FieldCache(str(tmp_path / "default"))
    cache.put("a" * 40, fld)
    cache.use_folder(str(tmp_path / "scene"))
    cache.put("b" * 40, fld)
    assert cache.clear() == 2
    cache.use_folder(None)
    assert cache.get("a" * 40, rig) is None
    assert os.listdir(tmp_path / "default") == []
    assert os.listdir(tmp_path / "scene") == []
