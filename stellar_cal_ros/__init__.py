"""stellar_cal_ros: online calibration of a star tracker + gyroscope/IMU system.

Layers (see ``doc/architecture.md``):

- :mod:`stellar_cal_ros.core`: numpy/scipy only -- rotations, camera model, strapdown
  propagation, Earth orientation, gravity, catalogue and astrometry.
- :mod:`stellar_cal_ros.effects`: one module per physical effect (the extension point).
- :mod:`stellar_cal_ros.methods`: estimators assembled from core + effects.
- :mod:`stellar_cal_ros.sim`: the truth-world simulator.
- :mod:`stellar_cal_ros.io`: MCAP bags and the calibration YAML.
- :mod:`stellar_cal_ros.nodes`: thin rclpy nodes.
"""

__version__ = "0.1.0"
