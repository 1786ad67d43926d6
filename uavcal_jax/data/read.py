"""Read any supported recording: an EuRoC/ASL folder, a ROS 1 bag or a ROS 2 bag folder.

:func:`read_sequence` tells the formats apart by the path alone (a ``.bag``/``.db3``/``.mcap``
file or a folder with ``metadata.yaml`` is a bag; any other folder is EuRoC/ASL) and hands it
to :func:`~uavcal_jax.data.euroc.read_euroc` or :func:`~uavcal_jax.data.rosbag.read_rosbag`,
whose docstrings give each format's bad-input policy.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.data.euroc import read_euroc
from uavcal_jax.data.rosbag import is_bag, read_rosbag
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.errors import DataError


def read_sequence(path: str | Path, *, strict: bool = False, imu_topic: str | None = None,
                  image_topics: list[str] | None = None) -> tuple[Sequence, str]:
    """Read the recording at ``path``; returns ``(sequence, format)``, format ``"euroc"`` or
    ``"rosbag"``.

    Args:
        path: an EuRoC/ASL folder (holding ``mav0``, or ``mav0`` itself), a ROS 1 ``.bag``
            file, or a ROS 2 bag folder (or its ``.db3``/``.mcap`` file).
        strict: raise :class:`~uavcal_jax.errors.DataError` instead of repairing.
        imu_topic, image_topics: bags only: the topics to read (default: found by type).

    Raises:
        DataError: ``path`` does not exist or is not a recording (the message names it), or
            the reader's own errors.
    """
    path = Path(path)
    if not path.exists():
        raise DataError("no such file or folder", path)
    if is_bag(path):
        return read_rosbag(path, imu_topic=imu_topic, image_topics=image_topics,
                           strict=strict), "rosbag"
    if not path.is_dir():
        raise DataError("not a recording (expected an EuRoC/ASL folder, a ROS 1 .bag file or "
                        "a ROS 2 bag folder)", path)
    return read_euroc(path, strict=strict), "euroc"
