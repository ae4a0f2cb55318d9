"""COLMAP dense arrays: the round trip, the byte layout of a hand-built asymmetric array, and COLMAP's own reader
(pycolmap's DepthMap / NormalMap) reading what is written."""

import numpy as np
import pycolmap
import pytest

from mvrecon.io.colmap_array import read_colmap_array, write_colmap_array


def test_round_trip_one_and_three_channels(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.random((5, 7)).astype(np.float32)
    normals = rng.normal(size=(5, 7, 3)).astype(np.float32)
    write_colmap_array(tmp_path / "d.bin", depth)
    write_colmap_array(tmp_path / "n.bin", normals)
    np.testing.assert_array_equal(read_colmap_array(tmp_path / "d.bin"), depth)
    np.testing.assert_array_equal(read_colmap_array(tmp_path / "n.bin"), normals)


def test_byte_layout_is_colmaps(tmp_path):
    # 3 wide, 2 high, 2 channels: value = 100*channel + 10*row + column, so every value says where it sits
    rows, cols, chans = np.meshgrid(np.arange(2), np.arange(3), np.arange(2), indexing="ij")
    array = (100 * chans + 10 * rows + cols).astype(np.float32)
    write_colmap_array(tmp_path / "a.bin", array)
    data = (tmp_path / "a.bin").read_bytes()
    assert data.startswith(b"3&2&2&")
    values = np.frombuffer(data[len(b"3&2&2&"):], dtype="<f4")
    # channel by channel, each row by row with x fastest
    np.testing.assert_array_equal(values, [0, 1, 2, 10, 11, 12, 100, 101, 102, 110, 111, 112])
    # COLMAP's scripts' read_array convention: reshape((W, H, C), order="F"), then (H, W, C)
    colmap = np.transpose(values.reshape((3, 2, 2), order="F"), (1, 0, 2))
    np.testing.assert_array_equal(colmap, array)


def test_pycolmap_reads_the_depth_and_normal_maps(tmp_path):
    rng = np.random.default_rng(1)
    depth = (1 + rng.random((6, 9))).astype(np.float32)
    normals = rng.normal(size=(6, 9, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    write_colmap_array(tmp_path / "d.bin", depth)
    write_colmap_array(tmp_path / "n.bin", normals)
    dm, nm = pycolmap.DepthMap(), pycolmap.NormalMap()
    dm.read(tmp_path / "d.bin")
    nm.read(tmp_path / "n.bin")
    np.testing.assert_array_equal(dm.to_array(), depth)
    assert (nm.width, nm.height) == (9, 6)
    # COLMAP's Mat keeps the channels one after another (value (row, col, c) at c*W*H + row*W + col), and
    # pycolmap 4.2.1's NormalMap.to_array hands out that buffer as it is, shaped (H, W, 3)
    np.testing.assert_array_equal(nm.to_array().ravel(), normals.transpose(2, 0, 1).ravel())


def test_a_file_that_is_not_an_array_is_named(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"hello world")
    with pytest.raises(ValueError, match="x.bin: not a COLMAP array"):
        read_colmap_array(tmp_path / "x.bin")
    (tmp_path / "short.bin").write_bytes(b"4&4&1&" + np.zeros(3, "<f4").tobytes())
    with pytest.raises(ValueError, match="short.bin: COLMAP array of 4x4x1 holds 3 values"):
        read_colmap_array(tmp_path / "short.bin")
