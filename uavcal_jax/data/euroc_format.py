"""The EuRoC ASL folder layout: folder and file names, CSV headers and column counts, units.

One definition shared by the reader (:mod:`uavcal_jax.data.euroc`) and the writer
(:mod:`uavcal_jax.data.euroc_writer`)::

    mav0/body.yaml
    mav0/cam0/{sensor.yaml, data.csv, data/<t_ns>.png}        8-bit gray or RGB frames
    mav0/cam1/...
    mav0/depth0/{sensor.yaml, data.csv, data/<t_ns>.png}      uint16 z-depth in millimetres
    mav0/depth1/...                                           (0 = no depth)
    mav0/imu0/{sensor.yaml, data.csv}                         EuRoC's 7-column IMU table
    mav0/state_groundtruth_estimate0/{sensor.yaml, data.csv}  EuRoC's 17-column states
    mav0/target0/{data.csv, classes.txt}                      see uavcal_jax.data.targets
"""

from __future__ import annotations

import re

#: The recording's top folder.
MAV0 = "mav0"
IMU_FOLDER = "imu0"
GROUND_TRUTH_FOLDER = "state_groundtruth_estimate0"
TARGET_FOLDER = "target0"
#: Every sensor folder's table and calibration, and an image stream's image folder.
DATA_CSV = "data.csv"
SENSOR_YAML = "sensor.yaml"
IMAGE_FOLDER = "data"
#: Camera (``cam0``, ``cam1`` ...) and depth (``depth0`` ...) stream folders.
CAMERA_FOLDER = re.compile(r"^cam\d+$")
DEPTH_FOLDER = re.compile(r"^depth\d+$")

#: ``data.csv`` header of image streams (cameras and depth).
IMAGE_HEADER = "#timestamp [ns],filename"
#: ``imu0/data.csv`` header, as in EuRoC: t, gyro xyz (rad/s), accel xyz (m/s^2).
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
#: ``state_groundtruth_estimate0/data.csv`` header, as in EuRoC: t, position xyz, quaternion
#: wxyz, velocity xyz, gyro bias xyz, accel bias xyz.
GROUND_TRUTH_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
    "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
    "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
#: Fields per row of each table (the timestamp included), as its header names them.
IMAGE_FIELDS = IMAGE_HEADER.count(",") + 1
IMU_FIELDS = IMU_HEADER.count(",") + 1
GROUND_TRUTH_FIELDS = GROUND_TRUTH_HEADER.count(",") + 1

#: Depth PNGs hold z-depth in these metres per unit (uint16 millimetres).
DEPTH_SCALE_M = 1e-3
