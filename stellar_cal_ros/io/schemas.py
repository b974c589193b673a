"""ros2msg schema texts of the contract message types, exactly as rosbag2 / mcap_ros2 store them.

Each text is the main definition followed by its dependencies, separated the way rosbag2 does
(a line of 80 ``=`` and ``MSG: pkg/Type``). The writer stores them in MCAP schema records; the
readers use them to register ``stellar_cal_msgs`` types when a bag carries no definitions.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = [
    "CALIBRATION_VIEW",
    "CALIBRATION_VIEW_SCHEMA",
    "CAMERA_INFO",
    "CAMERA_INFO_SCHEMA",
    "FLUID_PRESSURE",
    "FLUID_PRESSURE_SCHEMA",
    "IMAGE",
    "IMAGE_SCHEMA",
    "IMU",
    "IMU_SCHEMA",
    "NAVSATFIX",
    "NAVSATFIX_SCHEMA",
    "SCHEMA_TEXTS",
    "STAR_ARRAY",
    "STAR_CENTROID_ARRAY_SCHEMA",
    "TEMPERATURE",
    "TEMPERATURE_SCHEMA",
    "normalize_type",
]

_TIME_DEF = "int32 sec\nuint32 nanosec\n"
_HEADER_DEF = "builtin_interfaces/Time stamp\nstring frame_id\n"
_QUATERNION_DEF = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_VECTOR3_DEF = "float64 x\nfloat64 y\nfloat64 z\n"
_IMU_DEF = (
    "std_msgs/Header header\n"
    "geometry_msgs/Quaternion orientation\n"
    "float64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\n"
    "float64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\n"
    "float64[9] linear_acceleration_covariance\n"
)
_NAVSATSTATUS_DEF = (
    "int8 STATUS_UNKNOWN = -2\n"
    "int8 STATUS_NO_FIX =  -1\n"
    "int8 STATUS_FIX =      0\n"
    "int8 STATUS_SBAS_FIX = 1\n"
    "int8 STATUS_GBAS_FIX = 2\n"
    "int8 status -2\n"
    "uint16 SERVICE_UNKNOWN = 0\n"
    "uint16 SERVICE_GPS =     1\n"
    "uint16 SERVICE_GLONASS = 2\n"
    "uint16 SERVICE_COMPASS = 4\n"
    "uint16 SERVICE_GALILEO = 8\n"
    "uint16 service\n"
)
_NAVSATFIX_DEF = (
    "std_msgs/Header header\n"
    "NavSatStatus status\n"
    "float64 latitude\n"
    "float64 longitude\n"
    "float64 altitude\n"
    "float64[9] position_covariance\n"
    "uint8 COVARIANCE_TYPE_UNKNOWN = 0\n"
    "uint8 COVARIANCE_TYPE_APPROXIMATED = 1\n"
    "uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN = 2\n"
    "uint8 COVARIANCE_TYPE_KNOWN = 3\n"
    "uint8 position_covariance_type\n"
)
_TEMPERATURE_DEF = "std_msgs/Header header\nfloat64 temperature\nfloat64 variance\n"
_FLUID_PRESSURE_DEF = "std_msgs/Header header\nfloat64 fluid_pressure\nfloat64 variance\n"
_STAR_CENTROID_DEF = (
    "uint32 catalog_id\n"
    "float64 right_ascension\n"
    "float64 declination\n"
    "float64 u\n"
    "float64 v\n"
    "float32 magnitude\n"
    "float32 sigma\n"
)
_STAR_CENTROID_ARRAY_DEF = "std_msgs/Header header\nfloat32 exposure_time\nStarCentroid[] stars\n"
_IMAGE_DEF = (
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string encoding\n"
    "uint8 is_bigendian\n"
    "uint32 step\n"
    "uint8[] data\n"
)
_CAMERA_INFO_DEF = (
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string distortion_model\n"
    "float64[] d\n"
    "float64[9] k\n"
    "float64[9] r\n"
    "float64[12] p\n"
    "uint32 binning_x\n"
    "uint32 binning_y\n"
    "RegionOfInterest roi\n"
)
_ROI_DEF = (
    "uint32 x_offset\n"
    "uint32 y_offset\n"
    "uint32 height\n"
    "uint32 width\n"
    "bool do_rectify\n"
)
_PARAMETER_ESTIMATE_DEF = (
    "string name\n"
    "string unit\n"
    "float64 value\n"
    "float64 sigma\n"
    "float64 lo\n"
    "float64 hi\n"
)
_CALIBRATION_VIEW_DEF = (
    "std_msgs/Header header\n"
    "ParameterEstimate[] parameters\n"
    "uint32 updates\n"
    "float64 nis_frame\n"
    "float64 nis_moving\n"
    "float64 nis_band_lo\n"
    "float64 nis_band_hi\n"
    "float64 nis_window\n"
    "string verdict\n"
)


def _concat_definition(main: str, deps: Sequence[tuple[str, str]]) -> str:
    """Join a definition and its dependencies the way rosbag2 does (80 '=' and ``MSG:``)."""
    sep = "\n" + "=" * 80 + "\n"
    return main + "".join(f"{sep}MSG: {name}\n{text}" for name, text in deps)


_HDR_DEPS = [("std_msgs/Header", _HEADER_DEF), ("builtin_interfaces/Time", _TIME_DEF)]

IMU_SCHEMA = _concat_definition(
    _IMU_DEF,
    [("geometry_msgs/Quaternion", _QUATERNION_DEF), ("geometry_msgs/Vector3", _VECTOR3_DEF)]
    + _HDR_DEPS,
)
"""ros2msg schema text of ``sensor_msgs/msg/Imu``."""
NAVSATFIX_SCHEMA = _concat_definition(
    _NAVSATFIX_DEF, [("sensor_msgs/NavSatStatus", _NAVSATSTATUS_DEF)] + _HDR_DEPS
)
"""ros2msg schema text of ``sensor_msgs/msg/NavSatFix``."""
TEMPERATURE_SCHEMA = _concat_definition(_TEMPERATURE_DEF, _HDR_DEPS)
"""ros2msg schema text of ``sensor_msgs/msg/Temperature``."""
FLUID_PRESSURE_SCHEMA = _concat_definition(_FLUID_PRESSURE_DEF, _HDR_DEPS)
"""ros2msg schema text of ``sensor_msgs/msg/FluidPressure``."""
STAR_CENTROID_ARRAY_SCHEMA = _concat_definition(
    _STAR_CENTROID_ARRAY_DEF, _HDR_DEPS + [("stellar_cal_msgs/StarCentroid", _STAR_CENTROID_DEF)]
)
"""ros2msg schema text of ``stellar_cal_msgs/msg/StarCentroidArray``."""
IMAGE_SCHEMA = _concat_definition(_IMAGE_DEF, _HDR_DEPS)
"""ros2msg schema text of ``sensor_msgs/msg/Image``."""
CAMERA_INFO_SCHEMA = _concat_definition(
    _CAMERA_INFO_DEF, _HDR_DEPS + [("sensor_msgs/RegionOfInterest", _ROI_DEF)]
)
"""ros2msg schema text of ``sensor_msgs/msg/CameraInfo``."""
CALIBRATION_VIEW_SCHEMA = _concat_definition(
    _CALIBRATION_VIEW_DEF,
    _HDR_DEPS + [("stellar_cal_msgs/ParameterEstimate", _PARAMETER_ESTIMATE_DEF)],
)
"""ros2msg schema text of ``stellar_cal_msgs/msg/CalibrationView`` (the live view)."""

IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
TEMPERATURE = "sensor_msgs/msg/Temperature"
FLUID_PRESSURE = "sensor_msgs/msg/FluidPressure"
STAR_ARRAY = "stellar_cal_msgs/msg/StarCentroidArray"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
CALIBRATION_VIEW = "stellar_cal_msgs/msg/CalibrationView"

SCHEMA_TEXTS: dict[str, str] = {
    IMU: IMU_SCHEMA,
    NAVSATFIX: NAVSATFIX_SCHEMA,
    TEMPERATURE: TEMPERATURE_SCHEMA,
    FLUID_PRESSURE: FLUID_PRESSURE_SCHEMA,
    STAR_ARRAY: STAR_CENTROID_ARRAY_SCHEMA,
    IMAGE: IMAGE_SCHEMA,
    CAMERA_INFO: CAMERA_INFO_SCHEMA,
}
"""Schema name (``pkg/msg/Type``) -> full ros2msg text, for every type the writer produces."""


def normalize_type(name: str) -> str:
    """Map ``pkg/Type`` (ROS 1 style) to ``pkg/msg/Type``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name
