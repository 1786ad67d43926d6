"""Readers for real recordings (EuRoC ASL, TUM, ROS bags; :func:`read_sequence` for any of
them) and training windows."""

from uavcal_jax.data.euroc import (
    camera_calibration_from_yaml,
    imu_calibration_from_yaml,
    load_depth,
    load_image,
    read_euroc,
    read_ground_truth_csv,
    read_sensor_yaml,
)
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.rosbag import read_rosbag
from uavcal_jax.data.sequence import (
    CameraCalibration,
    FrameStream,
    GroundTruth,
    ImuCalibration,
    ImuData,
    Sequence,
)
from uavcal_jax.data.targets import TargetLabels, read_target_labels, write_target_labels
from uavcal_jax.data.tum import read_tum, write_tum
from uavcal_jax.data.windows import WindowConfig, WindowSet, load_frames, make_windows
from uavcal_jax.data.yaml_io import read_opencv_yaml

__all__ = [
    "CameraCalibration",
    "FrameStream",
    "GroundTruth",
    "ImuCalibration",
    "ImuData",
    "Sequence",
    "TargetLabels",
    "WindowConfig",
    "WindowSet",
    "camera_calibration_from_yaml",
    "imu_calibration_from_yaml",
    "load_depth",
    "load_frames",
    "load_image",
    "make_windows",
    "read_euroc",
    "read_ground_truth_csv",
    "read_opencv_yaml",
    "read_rosbag",
    "read_sequence",
    "read_sensor_yaml",
    "read_target_labels",
    "read_tum",
    "write_target_labels",
    "write_tum",
]
