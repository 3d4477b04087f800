from glob import glob

from setuptools import find_packages, setup

package_name = "has_control"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config/foxglove", glob("config/foxglove/*.json")),
        # ``ros2 run has_control plant`` (colcon): lib/has_control/<node>; pip puts only has-control* on PATH
        ("lib/" + package_name, glob("resource/ros2_run/*")),
    ],
    install_requires=["setuptools", "numpy", "numba", "matplotlib", "pyyaml", "rosbags", "zstandard", "cma", "scipy"],
    zip_safe=True,
    maintainer="has_control maintainers",
    maintainer_email="maintainers@has-control.dev",
    description="Adaptive back-stepping control of a hydraulic suspension actuator, tuned by PSO.",
    license="Apache-2.0",
    extras_require={"test": ["pytest", "mcap", "mcap-ros2-support", "foxglove-sdk", "websockets"],
                    "live": ["foxglove-sdk"],              # has-control stack --foxglove, foxglove_port
                    "dask": ["dask", "distributed"]},      # --dask: the batch evaluator on a Dask cluster
    entry_points={
        "console_scripts": [
            "has-control = has_control.cli:main",
            "has-control-plant = has_control.cli.main:plant",
            "has-control-controller = has_control.cli.main:controller",
            "has-control-tuner = has_control.cli.main:tuner",
        ],
    },
)
