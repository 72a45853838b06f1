"""Reading recordings: rosbag access and PointCloud2 decoding."""

from torchsoil.io.bag import BagError, Recording, read_recording
from torchsoil.io.pointcloud import Cloud, decode

__all__ = ["BagError", "Cloud", "Recording", "decode", "read_recording"]
