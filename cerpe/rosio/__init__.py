"""ROS messages without a ROS installation: decoded and built with ``rosbags``.

* :mod:`cerpe.rosio.types` -- the type store, the message type names cerpe reads and writes, CDR
  (de)serialisation with one clear error.
* :mod:`cerpe.rosio.decode` -- messages to what the algorithm takes: an ``Image`` or
  ``CompressedImage`` to ``[H,W,3] uint8`` RGB, a depth ``Image`` to metres, a ``CameraInfo`` to
  intrinsics and distortion, ``Odometry``, ``PoseStamped`` and ``TransformStamped`` to 4x4 poses.
* :mod:`cerpe.rosio.encode` -- the other way (bags written from a dataset, test publishers).
* :mod:`cerpe.rosio.tf` -- a small TF buffer: a static camera extrinsic and ``odom -> base_link``.
* :mod:`cerpe.rosio.bags` -- reading ROS 1 ``.bag`` and ROS 2 (folder, ``.db3``, ``.mcap``) bags,
  writing ROS 2 bags.

Conventions: image frames are optical frames (x right, y down, z forward: OpenCV's axes); a pose
``T_a_b`` maps points of frame ``b`` into frame ``a``; stamps are seconds (float) of the message
header. Nothing here knows about Zenoh, runs or the algorithm.
"""
from .types import RosInputError

__all__ = ["RosInputError"]
