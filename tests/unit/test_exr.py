"""io.exr: float channels round-trip, compressed or not."""

import numpy as np
import pytest

from multiscale_camera.io.exr import ExrError, read_channels, write_channels


@pytest.mark.parametrize("compress", [True, False])
def test_channels_round_trip(tmp_path, compress):
    rng = np.random.default_rng(5)
    channels = {c: rng.normal(size=(7, 11)).astype(np.float32) for c in "RGBA"}
    channels["R"][0, 0] = 1e35  # the hand-off's mark for a texel without a ray
    path = tmp_path / "t.exr"
    write_channels(path, channels, compress=compress)
    back, header = read_channels(path)
    assert sorted(back) == sorted(channels)
    for name, values in channels.items():
        np.testing.assert_array_equal(back[name], values)
    assert ("ZIP" in str(header["compression"])) == compress
    assert ("NO_COMPRESSION" in str(header["compression"])) == (not compress)


def test_mismatched_shapes_are_refused(tmp_path):
    with pytest.raises(ExrError):
        write_channels(tmp_path / "t.exr", {"R": np.zeros((2, 3)), "G": np.zeros((3, 2))})
