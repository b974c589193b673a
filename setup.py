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

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=data_files,
    python_requires=">=3.10",
    install_requires=["setuptools"],
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
