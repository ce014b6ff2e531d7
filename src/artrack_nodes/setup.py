"""ament_python packaging: node executables land in lib/artrack_nodes, where `ros2 run` looks."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "artrack_nodes"

NODES = [
    "camera_ingest",
    "blob_features",
    "edge_features",
    "skeleton",
    "feedback_projection",
    "bag_player",
    "bag_recorder",
    "body_publisher",
    "loose_limbed",
    "particle_tracker",
    "object_features",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("../../config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="artrack developers",
    maintainer_email="artrack@example.org",
    description="Closed-loop multi-camera articulated body tracking (ROS 2 nodes and core).",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [f"{n} = {PACKAGE}.{n}:main" for n in NODES]
        + ["artrack = artrack.cli:main"],
    },
)
