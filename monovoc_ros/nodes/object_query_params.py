"""The parameters the object component (nodes.object_query) adds to the node: one specification each
(nodes.param_spec), with the object index's own defaults (IndexConfig). `config/object_query.yaml` and
the README table list them (a test checks both)."""

from __future__ import annotations

from monovoc_ros.embed.backend import BACKENDS
from monovoc_ros.nodes.param_spec import Param
from monovoc_ros.objects.approach import MAX_STANDOFF_M, RobotShape
from monovoc_ros.objects.index import CROP_MODES, LIVE_OBJECTS_PER_REFRESH, UP_AXES, IndexConfig

_INDEX = IndexConfig()
_SHAPE = RobotShape()
NAVIGATION_MODES = ("none", "goal_topic", "nav2")

# Order = order in config/object_query.yaml and in the README table.
PARAMETERS: tuple[Param, ...] = (
    Param("query.top_k", _INDEX.default_top_k, "objects returned when a TextQuery asks for top_k = 0", low=1),
    Param("query.max_text_chars", _INDEX.max_query_chars, "longer query texts are truncated (the answer's message says so), longer questions (ask) refused", low=1),
    Param("query.highlight", True, "publish query/highlight (Gaussians) and query/markers for answers"),
    Param("query.highlight_rate_hz", 5.0, "max highlight publications per second (the newest answer wins)", above=0),
    Param("objects.backend", "conse", "embedding backend: 'conse' (offline default) or 'clip_onnx' (user-supplied)", choices=BACKENDS),
    Param("objects.model_dir", "", "embedding model directory (empty: ~/.cache/monovoc_ros/models)"),
    Param("objects.crop_mode", _INDEX.crop_mode, "object crops: 'soft' (context dimmed) or 'hard' (object only)", choices=CROP_MODES),
    Param("objects.views_per_object", _INDEX.views_per_object, "best keyframe views kept per object (by mask pixel count)", low=1),
    Param("objects.description_weight", _INDEX.description_weight, "share of the attribute description in each object's embedding (0-1)", low=0, high=1),
    Param("objects.label_weight", _INDEX.label_weight, "a text naming an object's label ranks it up by this x the label's confidence (0 = embedding only)", low=0, high=2),
    Param("objects.min_gaussians", _INDEX.min_gaussians, "objects with fewer Gaussians are not listed", low=1),
    Param("objects.up_axis", _INDEX.up_axis, "up direction for sizes and heights: +x..-z, or 'auto' (cameras + flat surfaces)", choices=UP_AXES),
    Param("objects.max_objects_per_refresh", LIVE_OBJECTS_PER_REFRESH, "objects (re-)embedded per chunk of work", low=1),
    # Going to objects (the go_to action and the approach_pose service; monovoc_ros/objects/approach.py)
    Param("navigation.mode", "none", "go_to: 'nav2' drives through Nav2's navigate_to_pose, 'goal_topic' publishes the pose on navigation.goal_topic, 'none' only answers", choices=NAVIGATION_MODES),
    Param("navigation.goal_topic", "/goal_pose", "PoseStamped topic of navigation.mode goal_topic (what RViz's Nav2 Goal tool and bt_navigator use)"),
    Param("navigation.nav2_action", "/navigate_to_pose", "Nav2's NavigateToPose action (navigation.mode nav2)"),
    Param("navigation.nav2_wait_s", 5.0, "how long go_to waits for Nav2's action server before failing", above=0),
    Param("navigation.goal_frame", "", "frame_id of approach poses (empty: frame_id, the gaussians topic's map frame; no tf here)"),
    Param("approach.standoff", 0.6, "metres between the robot and the object's footprint when a request gives 0", above=0, high=MAX_STANDOFF_M),
    Param("approach.robot_radius", _SHAPE.robot_radius, "metres: obstacles are inflated by this", low=0),
    Param("approach.robot_height", _SHAPE.robot_height, "metres above the floor: higher Gaussians are passed under", above=0),
    Param("approach.min_obstacle_height", _SHAPE.min_obstacle_height, "metres above the floor: lower Gaussians are floor", low=0),
    Param("approach.cell", _SHAPE.cell, "free-space grid resolution, metres", above=0),
)  # fmt: skip
