"""uavcal-jax: camera-based IMU calibration, stereo VIO and target detection for UAVs.

Packages (arrows point one way): ``cli``/``experiments`` -> task packages (``calib``,
``vio``, ``detect``, ``track``) -> shared numerics (``imu``, ``geometry``). ``data`` and
``sim`` produce arrays and know nothing of models.
"""

__version__ = "0.1.0"
