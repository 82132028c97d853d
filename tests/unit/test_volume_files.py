"""Volume file readers: .npy, .raw, .nrrd (raw, gzip, detached), and their bad input."""

import gzip

import numpy as np
import pytest

from multiscale_camera.core.errors import VolumeError
from multiscale_camera.io import volume_files as F


@pytest.fixture
def data():
    rng = np.random.default_rng(1)
    return rng.integers(0, 60000, size=(5, 4, 3)).astype(np.uint16)


def test_raw_is_x_fastest(tmp_path, data):
    path = tmp_path / "v.raw"
    # x fastest: voxel (x, y, z) at ((z * ny) + y) * nx + x
    flat = [data[x, y, z] for z in range(3) for y in range(4) for x in range(5)]
    np.array(flat, dtype="<u2").tofile(path)
    got = F.read_volume(str(path), (5, 4, 3), "UINT16", little_endian=True)
    np.testing.assert_array_equal(got, data)
    np.array(flat, dtype=">u2").tofile(path)
    np.testing.assert_array_equal(F.read_raw(str(path), (5, 4, 3), "UINT16", False), data)


def test_raw_of_the_wrong_size(tmp_path, data):
    path = tmp_path / "v.raw"
    data.astype("<u2").tofile(path)
    with pytest.raises(VolumeError) as err:
        F.read_raw(str(path), (5, 4, 4), "UINT16")
    assert str(err.value) == (
        "'v.raw' holds 120 bytes, but 5x4x4 voxels of uint16 need 160: "
        "check the dimensions and the value type"
    )


def test_missing_file(tmp_path):
    path = str(tmp_path / "nothing.nrrd")
    with pytest.raises(VolumeError) as err:
        F.read_volume(path)
    assert str(err.value) == f"The volume file '{path}' does not exist"


def test_unknown_extension(tmp_path):
    with pytest.raises(VolumeError, match="'v.tif' is not a volume file this add-on reads"):
        F.read_volume(str(tmp_path / "v.tif"))


def test_npy(tmp_path, data):
    path = tmp_path / "v.npy"
    np.save(path, data)
    np.testing.assert_array_equal(F.read_volume(str(path)), data)
    np.save(path, data[0])
    with pytest.raises(VolumeError, match="a volume needs a 3D array of numbers"):
        F.read_volume(str(path))


@pytest.mark.parametrize("level", [0, 6])
def test_nrrd_round_trip(tmp_path, data, level):
    path = tmp_path / "v.nrrd"
    F.write_nrrd(path, data, gzip_level=level)
    np.testing.assert_array_equal(F.read_volume(str(path)), data)


def test_nrrd_written_by_hand(tmp_path, data):
    """A header as other tools write it: comments, key-value pairs, big-endian floats,
    gzip, a four-axis array with a first axis of one, space directions."""
    values = data.astype(np.float32) / 7
    body = gzip.compress(np.ascontiguousarray(values.transpose(2, 1, 0)).astype(">f4").tobytes())
    header = (
        b"NRRD0005\n# made by hand\ntype: float\ndimension: 4\nsizes: 1 5 4 3\n"
        b"space: left-posterior-superior\nspace directions: none (1,0,0) (0,1,0) (0,0,1)\n"
        b"encoding: gzip\nendian: big\nmodality:=CT\n\n"
    )
    path = tmp_path / "v.nrrd"
    path.write_bytes(header + body)
    np.testing.assert_allclose(F.read_volume(str(path)), values)


def test_detached_nrrd(tmp_path, data):
    (tmp_path / "v.raw").write_bytes(np.ascontiguousarray(data.transpose(2, 1, 0)).tobytes())
    hdr = tmp_path / "v.nhdr"
    hdr.write_text(
        "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 5 4 3\nencoding: raw\n"
        "endian: little\ndata file: v.raw\n\n"
    )
    np.testing.assert_array_equal(F.read_volume(str(hdr)), data)
    hdr.write_text(hdr.read_text().replace("v.raw", "gone.raw"))
    with pytest.raises(VolumeError, match="names the data file 'gone.raw', which does not exist"):
        F.read_volume(str(hdr))


def test_truncated_nrrd(tmp_path, data):
    path = tmp_path / "v.nrrd"
    F.write_nrrd(path, data, gzip_level=0)
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(VolumeError, match="the file is truncated"):
        F.read_volume(str(path))
