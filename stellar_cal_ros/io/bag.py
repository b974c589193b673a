"""Bags in and out: the names callers use, gathered from the modules that implement them.

- :mod:`stellar_cal_ros.core.types`: the domain types (:class:`ImuSeries`, :class:`StarFrame`,
  :class:`ScalarSeries`, :class:`NavSatSeries`, :class:`TopicInfo`);
- :mod:`stellar_cal_ros.io.reader`: :class:`BagReader` (one ``.mcap``, rosbag2 directories,
  ROS 1 bags; ``read_*``, ``stream``, ``check``);
- :mod:`stellar_cal_ros.io.writer`: :class:`BagWriter` (MCAP, rosbag2 ``ros2`` profile);
- :mod:`stellar_cal_ros.io.schemas`: the ros2msg schema texts;
- :mod:`stellar_cal_ros.io.mcap_container`, :mod:`~stellar_cal_ros.io.mcap_records`,
  :mod:`~stellar_cal_ros.io.cdr`, :mod:`~stellar_cal_ros.io.sources`,
  :mod:`~stellar_cal_ros.io.rosbags_source`: the container, the CDR codecs and the sources.
"""

from __future__ import annotations

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame, TopicInfo
from stellar_cal_ros.errors import BagError, MessageDecodeError
from stellar_cal_ros.io.mcap_records import BagProblem
from stellar_cal_ros.io.reader import DEFAULT_TOPICS, BagReader, OnError
from stellar_cal_ros.io.schemas import (
    FLUID_PRESSURE_SCHEMA,
    IMU_SCHEMA,
    NAVSATFIX_SCHEMA,
    SCHEMA_TEXTS,
    STAR_CENTROID_ARRAY_SCHEMA,
    TEMPERATURE_SCHEMA,
)
from stellar_cal_ros.io.writer import BagWriter

__all__ = [
    "DEFAULT_TOPICS",
    "FLUID_PRESSURE_SCHEMA",
    "IMU_SCHEMA",
    "NAVSATFIX_SCHEMA",
    "SCHEMA_TEXTS",
    "STAR_CENTROID_ARRAY_SCHEMA",
    "TEMPERATURE_SCHEMA",
    "BagError",
    "BagProblem",
    "BagReader",
    "BagWriter",
    "ImuSeries",
    "MessageDecodeError",
    "NavSatSeries",
    "OnError",
    "ScalarSeries",
    "StarFrame",
    "TopicInfo",
]
