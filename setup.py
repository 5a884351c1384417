import os

from setuptools import find_packages, setup

package_name = "monovoc_ros"


def share_tree(*folders: str) -> list[tuple[str, list[str]]]:
    """(share/monovoc_ros/<dir>, [files]) for every directory under ``folders``.

    data_files takes files only: a plain ``glob("config/*")`` also matched the directory
    config/queries, which made ``colcon build`` (setup.py install_data) fail with
    "can't copy 'config/queries': doesn't exist or not a regular file".
    """
    entries = []
    for folder in folders:
        for directory, subdirs, files in os.walk(folder):
            subdirs[:] = sorted(d for d in subdirs if d != "__pycache__")
            if files:
                entries.append((f"share/{package_name}/{directory}", sorted(f"{directory}/{f}" for f in files)))
    return entries


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["monovoc_ros", "monovoc_ros.*", "msg_adapters", "msg_adapters.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        # config/ (parameter files, query sets), launch/monovoc.launch.py, rviz/monovoc.rviz
        *share_tree("config", "launch", "rviz"),
    ],
    install_requires=["setuptools"],
    package_data={"monovoc_ros.embed": ["data/*.txt"]},
    zip_safe=True,
    maintainer="MonoVoc ROS developers",
    maintainer_email="monovoc@example.com",
    description="Open-vocabulary object-level semantic mapping on 3D Gaussian Splatting maps.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "monovoc = monovoc_ros.cli:main",
            # ros2 run monovoc_ros semantic_mapper: mapping + object database + /monovoc/query
            "semantic_mapper = monovoc_ros.nodes.entry:semantic_mapper",
            # the mapping node alone, without objects and embeddings (no models needed)
            "mapping_node = monovoc_ros.nodes.entry:mapping_node",
            # keyframe images -> per-frame instance masks + class names (a robot with only a camera)
            "segmenter = monovoc_ros.nodes.entry:segmenter",
        ],
    },
)
