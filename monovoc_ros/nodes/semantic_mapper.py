"""The full node `semantic_mapper`: mapping, object database and text-query service in one process.

    semantic_mapper --ros-args --params-file config/semantic_mapper.yaml --params-file config/object_query.yaml
    python -m monovoc_ros.nodes.semantic_mapper --ros-args -p map_directory:=/maps/office ...

composes the mapping node (monovoc_ros.nodes.mapping_node: topics, services, the mapping worker) with the
object-query component (monovoc_ros.nodes.object_query: objects, embeddings, objects.db, `query`, `ask`)
and the navigation component (monovoc_ros.nodes.navigation: `go_to`, `approach_pose`), wired
through the interface of monovoc_ros.nodes.component, as rclpy's executor examples compose nodes. The
mapping node alone is `mapping_node`.

Robot usage::

    ros2 service call /monovoc/query monovoc_interfaces/srv/TextQuery "{text: 'chair', top_k: 3}"
    monovoc query "chair" --top-k 3          # the same without the ros2 CLI
"""

from __future__ import annotations

import sys

from monovoc_ros.nodes.component import Component
from monovoc_ros.nodes.mapping_node import MappingNode, run
from monovoc_ros.nodes.navigation import NavigationComponent
from monovoc_ros.nodes.object_query import ObjectQueryComponent, read_settings


def compose(node: MappingNode) -> list[Component]:
    """The components of the full node beside ``node``: the object database and query service, whose
    parameters are declared on the mapping node (one parameter set per process, as the YAML files have it)."""
    host = node.host()
    settings = read_settings(node, host.labels)
    objects = ObjectQueryComponent(host, settings)
    return [objects, NavigationComponent(host, settings.navigation, lambda: objects.index, objects.labelled_map)]


def main(args: list[str] | None = None) -> int:
    return run(args, compose)


if __name__ == "__main__":
    sys.exit(main())
