"""`monovoc approach --map DIR TEXT`: where a robot should stand to reach the object TEXT names (offline).

    monovoc approach --map DIR "the sofa" [--standoff 0.6] [--json] [--plot out.png]

Exit codes: 0 a pose, 1 no pose (the message says why), 2 an unreadable map.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from monovoc_ros.commands.argument_types import non_negative, positive


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "approach",
        help="the pose to stand at beside the object a text names (a 2D free-space grid from the Gaussian map)",
        description="Builds the free-space grid of a saved map's Gaussians on its floor plane, picks the object "
        "TEXT names (relations read, as monovoc query) and prints the free cell reachable from the last keyframe's "
        "position closest to --standoff metres from the object, with a clear view, facing it "
        "(monovoc_ros/objects/approach.py).",
    )
    p.add_argument("text", help="e.g. 'the sofa', 'the chair next to the table'")
    p.add_argument("--map", metavar="DIR", required=True, help="a saved map directory (snapshot and objects.db)")
    # Checked in run (objects.approach.check_standoff), with the range in the message.
    p.add_argument("--standoff", type=float, default=0.6, help="metres from the object (default 0.6)")
    # Defaults: objects.approach.RobotShape's (imported in run: building the parser stays light).
    p.add_argument("--robot-radius", type=non_negative, help="inflation, metres (default 0.25)")
    p.add_argument("--robot-height", type=positive, help="metres; higher is passed under (default 1.2)")
    p.add_argument("--min-obstacle-height", type=non_negative, help="metres; lower is floor (default 0.1)")
    p.add_argument("--frame-id", default="map", help="frame of the printed pose (default map)")
    p.add_argument("--json", action="store_true", help='print {"success", "message", "pose", "object"}')
    p.add_argument("--plot", metavar="PNG", help="draw the grid, the objects and the pose into this image")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.core.map_store import MapStoreError, load_snapshot
    from monovoc_ros.embed.model_store import ModelMissingError
    from monovoc_ros.objects import approach as ap
    from monovoc_ros.objects.database import ObjectDatabaseError, load_object_index
    from monovoc_ros.objects.records import QueryError

    given = {"robot_radius": args.robot_radius, "robot_height": args.robot_height,
             "min_obstacle_height": args.min_obstacle_height}  # fmt: skip
    try:
        shape = ap.RobotShape(**{k: v for k, v in given.items() if v is not None})
        ap.check_standoff(args.standoff, "--standoff")  # before the work, not after it
        if args.plot and not Path(args.plot).resolve().parent.is_dir():  # checked before the work, not after it
            raise ValueError(f"--plot {args.plot}: no such directory {Path(args.plot).resolve().parent}")
        if args.plot and Path(args.plot).is_dir():  # matplotlib would write DIR.png beside it
            raise ValueError(
                f"--plot {args.plot}: a directory; give the image's name, e.g. {Path(args.plot) / 'approach.png'}"
            )
    except ValueError as exc:
        print(f"monovoc approach: {exc}", file=sys.stderr)
        return 1
    try:
        mapper = load_snapshot(args.map)
        index = load_object_index(args.map)
    except (MapStoreError, ObjectDatabaseError, OSError) as exc:
        print(f"monovoc approach: {exc}", file=sys.stderr)
        return 2
    gaussians, ids = mapper.gaussians, mapper.result().object_ids
    robot = None if index.viewpoint is None else index.viewpoint[:3, 3]
    try:
        grid = ap.free_space(gaussians.means, gaussians.opacities, index.up_vector(), index.floor_height(), shape)
        goal = ap.goal_for_text(index, args.text, grid, gaussians.means, ids, args.standoff, robot, shape.robot_height)
    except (QueryError, ModelMissingError) as exc:  # an empty text, no embedding models
        print(f"monovoc approach: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:  # no floor, no Gaussians
        goal = ap.Goal(ap.Approach(False, str(exc)))
        grid = None
    answer = goal.to_dict(args.frame_id)
    plotted = True
    if args.plot and grid is not None:
        named = [(r.label or r.hex, gaussians.means[ids == r.id]) for r in index.records()]
        name = goal.record.label if goal.record is not None else ""
        try:
            ap.plot(grid, args.plot, named, [(name, goal.approach)], robot)
        except (OSError, ValueError) as exc:  # not writable; an image format matplotlib does not write
            print(f"monovoc approach: --plot {args.plot}: {exc}", file=sys.stderr)
            plotted = False  # the answer is still printed
    if args.json:
        print(json.dumps(answer, indent=1))
    elif answer["success"]:
        pose = answer["pose"]
        x, y, z = pose["position"]
        print(
            f"{goal.approach.message}\ngo to ({x:.2f}, {y:.2f}, {z:.2f}) in {args.frame_id}, yaw {pose['yaw']:.2f} rad"
        )
    else:
        print(f"monovoc approach: {answer['message']}", file=sys.stderr)
    return 0 if answer["success"] and plotted else 1
