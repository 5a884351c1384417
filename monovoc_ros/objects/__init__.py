"""Objects of a semantic map and their language embeddings (METHOD section 5), without ROS.

- ``views``: the best keyframe views of each object (top-k by prevalence, bounded memory).
- ``index``: one embedding per object, incremental refresh, text queries (``records``: what it returns).
- ``geometry``: which Gaussians shape an object (confident ones in its main spatial cluster).
- ``upright``: sizes and heights in a gravity-aligned frame; the up direction of a map.
- ``labels``: class names as nouns for descriptions (ids and labels.json: ``core.evidence.palette``).
- ``database``: the SQLite object database (``objects.db`` in the map directory).
- ``build``: building an index offline from a mapper and keyframes.
- ``evaluation``: the paper's retrieval protocol (top-1 / top-3 of text queries).
- ``memory``: bytes of semantic state per scene.
"""

from monovoc_ros.objects.index import IndexConfig, ObjectIndex, RefreshReport, lazy_backend
from monovoc_ros.objects.records import ObjectRecord, QueryError, QueryResult
from monovoc_ros.objects.views import ObjectView, ObjectViews, ViewConfig

__all__ = [
    "IndexConfig",
    "ObjectIndex",
    "ObjectRecord",
    "ObjectView",
    "ObjectViews",
    "QueryError",
    "QueryResult",
    "RefreshReport",
    "ViewConfig",
    "lazy_backend",
]
