"""Bags from the zstd storage presets of `ros2 bag record` read like uncompressed ones."""
import numpy as np
from mcap.writer import CompressionType

from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.io import bag_writing as bag_module
from kpi_calib_ros.io.bag import read_bag, write_bag


def test_zstd_chunks_round_trip(tmp_path, monkeypatch):
    q = np.array([[0.1, 0.2], [0.3, -0.4]])
    joints, points = synthesize_streams(q, ['a', 'b'], np.ones((2, 3)), 'laser_tracker')
    original = bag_module.McapWriter

    def zstd_writer(stream, **kwargs):
        kwargs['compression'] = CompressionType.ZSTD
        return original(stream, **kwargs)
    monkeypatch.setattr(bag_module, 'McapWriter', zstd_writer)
    path = write_bag(tmp_path / 'zstd.mcap', joints, points)
    assert b'zstd' in path.read_bytes()
    got_joints, got_points = read_bag(path)
    assert [s.stamp_ns for s in got_joints] == [s.stamp_ns for s in joints]
    assert np.array_equal(np.array([p.xyz for p in got_points]), np.array([p.xyz for p in points]))
