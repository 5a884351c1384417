"""`monovoc eval`: the paper's rendered-segmentation evaluation of a semantic map (METHOD section 6)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from monovoc_ros.commands.argument_types import at_least, positive
from monovoc_ros.commands.sources import add_source_options, check_source_options, input_errors, open_source_args
from monovoc_ros.core.evaluation.evaluation import SegmentationEvaluator, render_point_labels, render_splat_labels
from monovoc_ros.core.evaluation.instance_eval import renamed, score_matched
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, labels_from_entries, pack_rgb
from monovoc_ros.core.evidence.quantize import METRICS
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.core.mapping import label_gaussians

PROTOCOLS = ("points", "splats")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="mismatch ratio and mIoU of a semantic map's renderings against reference masks",
        description="Renders the semantic map into keyframes and compares with the reference masks, for "
        "every quantization metric. Protocol 'points' is the paper's: Gaussian centres drawn as discs of "
        "world radius --point-size, nearest first. Protocol 'splats' renders the labels through the "
        "Gaussians (alpha compositing), as the map itself renders. Synthetic sources are compared with "
        "their clean ground-truth masks, and also scored with ground-truth labels (the protocol's ceiling).",
    )
    p.add_argument("map_dir", help="a map directory written by `monovoc map` or the node")
    add_source_options(p)
    p.add_argument("--every", type=at_least(1), default=3, help="evaluate every N-th keyframe (default 3)")
    p.add_argument("--metrics", default="all", help=f"comma-separated subset of {','.join(METRICS)} or all")
    p.add_argument("--protocols", default="points,splats", help="points, splats or both (default)")
    p.add_argument("--point-size", type=positive, default=0.05, help="disc world radius, metres (default 0.05)")
    p.add_argument("-o", "--out", default=None, help="JSON report path (default MAP_DIR/eval.json)")
    p.add_argument("--figure", default=None, help="PNG figure path (default MAP_DIR/eval.png)")
    p.set_defaults(func=run)


def _frames(args: argparse.Namespace):
    """(name, frames [(intrinsics, pose, reference mask)], labels {id: name}, ground truth ids or None)."""
    if args.bag:
        from monovoc_ros.bags import bag_labels

        frames = bag_frames(args.bag, args.every, args.max_keyframes)
        return Path(args.bag).name, frames, labels_from_entries(bag_labels(args.bag)), None
    seq = open_source_args(args)
    return sequence_frames(seq, args.every, args.max_keyframes)


def bag_frames(path, every: int = 1, max_keyframes: int | None = None) -> list:
    """Frames [(intrinsics, pose, mask)] of every ``every``-th of the first ``max_keyframes`` keyframes of a bag."""
    from monovoc_ros.bags import bag_events
    from monovoc_ros.core.keyframe import Keyframe

    keyframes = [e for e in bag_events(path) if isinstance(e, Keyframe)][:max_keyframes][::every]
    return [(k.intrinsics, k.cam_to_world, k.mask) for k in keyframes]


def sequence_frames(seq, every: int = 1, max_keyframes: int | None = None):
    """Frames of a sequence; synthetic scenes give their clean masks and per-Gaussian ground truth."""
    n = len(seq) if max_keyframes is None else min(len(seq), max_keyframes)
    frames = []
    for i in range(0, n, every):
        kf = seq.keyframe(i)
        reference = seq.clean_mask(i) if hasattr(seq, "clean_mask") else kf.mask
        frames.append((kf.intrinsics, kf.cam_to_world, reference))
    truth = None
    if hasattr(seq, "gaussian_object"):
        palette = np.array([o.palette_rgb for o in seq.objects], np.uint8)
        truth = np.full(len(seq.gaussian_object), UNOBSERVED_ID, np.uint32)
        labelled = seq.gaussian_object >= 0
        truth[labelled] = pack_rgb(palette[seq.gaussian_object[labelled]])
    return seq.name, frames, labels_from_entries(seq.labels()), truth


def score(gaussians, object_ids, frames, protocol: str, point_size: float) -> tuple[dict, list[np.ndarray]]:
    evaluator = SegmentationEvaluator()
    rendered = []
    for intrinsics, pose, reference in frames:
        if protocol == "points":
            pred = render_point_labels(gaussians.means, object_ids, intrinsics, pose, point_size=point_size)
        else:
            pred = render_splat_labels(gaussians, object_ids, intrinsics, pose)
        evaluator.update(pred, pack_rgb(reference))
        rendered.append(pred)
    return evaluator.result(), rendered


def _instances(match, object_ids: np.ndarray) -> dict:
    """The instance-matching figures of a per-frame map (core.evaluation.instance_eval)."""
    return {
        "matched_objects": len(match.mapping),
        "map_objects": match.objects,
        "map_objects_all": int(np.unique(object_ids[object_ids != UNOBSERVED_ID]).size),
        "reference_objects": match.reference_objects,
        "merges": match.merges,
        "splits": match.splits,
    }


def _public(result: dict, names: dict[int, str]) -> dict:
    per_object = {
        f"{oid:06x}": {"name": names.get(int(oid), ""), "iou": round(float(iou), 4)}
        for oid, iou in sorted(result["iou"].items())
    }
    return {
        "miou": round(float(result["miou"]), 4),
        "mismatch_all": round(float(result["mismatch_all"]), 4),
        "mismatch_nonwhite": round(float(result["mismatch_nonwhite"]), 4),
        "mismatched_pixels": int(result["mismatched"]),
        "pixels": int(result["pixels"]),
        "objects": per_object,
    }


def run(args: argparse.Namespace) -> int:
    try:
        return _eval(args)
    except input_errors() as exc:
        raise SystemExit(f"monovoc eval: {exc}") from None


def _eval(args: argparse.Namespace) -> int:
    if bool(args.source) == bool(args.bag):
        raise SystemExit("monovoc eval: give either SOURCE or --bag BAG")
    check_source_options(args)
    metrics = METRICS if args.metrics == "all" else tuple(m.strip() for m in args.metrics.split(","))
    protocols = tuple(p.strip() for p in args.protocols.split(","))
    for bad in set(metrics) - set(METRICS) | set(protocols) - set(PROTOCOLS):
        raise SystemExit(f"monovoc eval: unknown metric or protocol {bad!r}")
    start = time.perf_counter()
    mapper = load_snapshot(args.map_dir)
    name, frames, names, truth = _frames(args)
    palette = mapper.palette_builder.build()
    report: dict = {"map": str(args.map_dir), "source": name, "frames": len(frames), "point_size": args.point_size}
    figure_rows = None
    if mapper.config.semantic_mode == "vote":
        # Votes are labelled by argmax; the metric only snapped non-palette pixels while mapping.
        metrics = (mapper.config.metric,)
    for metric in metrics:
        result = (
            mapper.result() if mapper.config.semantic_mode == "vote" else label_gaussians(mapper.state, palette, metric)
        )
        entry: dict = {}
        object_ids = result.object_ids
        for protocol in protocols:
            scores, rendered = score(mapper.gaussians, result.object_ids, frames, protocol, args.point_size)
            entry[protocol] = _public(scores, names)
            if mapper.config.mask_ids == "per_frame":
                # The map's ids are its own: score after matching its objects to the reference instances.
                scores, match = score_matched(rendered, [pack_rgb(f[2]) for f in frames])
                entry[protocol] = {**_public(scores, names), **_instances(match, result.object_ids)}
                object_ids = np.where(result.observed, renamed(result.object_ids, match.mapping), UNOBSERVED_ID)
            if metric == mapper.config.metric and figure_rows is None:
                figure_rows = (protocol, rendered, scores)
        if truth is not None and len(truth) == len(mapper.gaussians):
            observed = result.observed & (truth != UNOBSERVED_ID)
            entry["gaussian_accuracy"] = round(float((object_ids[observed] == truth[observed]).mean()), 4)
        report[metric] = entry
    if truth is not None and len(truth) == len(mapper.gaussians):
        report["ground_truth_labels"] = {
            p: _public(score(mapper.gaussians, truth, frames, p, args.point_size)[0], names) for p in protocols
        }
    report["seconds"] = round(time.perf_counter() - start, 1)
    figure = Path(args.figure or Path(args.map_dir) / "eval.png")
    if figure_rows is not None:
        write_figure(figure, frames, figure_rows, names, mapper.config.metric)
    out = Path(args.out or Path(args.map_dir) / "eval.json")
    out.write_text(json.dumps(report, indent=1))  # last: a report means the evaluation is complete
    print(_table(report, metrics, protocols))
    if mapper.config.mask_ids == "per_frame":
        for protocol in protocols:
            e = report[mapper.config.metric][protocol]
            print(
                f"per-frame ids, {protocol}: matched mIoU {100 * e['miou']:.2f}%, {e['map_objects']} objects "
                f"({e['reference_objects']} reference), {e['merges']} merges, {e['splits']} splits"
            )
    print(f"report: {out}\nfigure: {figure}")
    return 0


def _table(report: dict, metrics, protocols) -> str:
    lines = [f"{'metric':10s} " + " ".join(f"{p + ' mIoU':>12s} {p + ' err(nw)':>14s}" for p in protocols)]
    rows = [(m, report[m]) for m in metrics]
    if "ground_truth_labels" in report:
        rows.append(("(truth)", report["ground_truth_labels"]))
    for m, entry in rows:
        cells = " ".join(
            f"{100 * entry[p]['miou']:11.2f}% {100 * entry[p]['mismatch_nonwhite']:13.2f}%" for p in protocols
        )
        lines.append(f"{m:10s} {cells}")
    return "\n".join(lines)


def write_figure(path: Path, frames, rows, names: dict[int, str], metric: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from monovoc_ros.core.evidence.palette import unpack_rgb

    protocol, rendered, scores = rows
    picks = np.linspace(0, len(frames) - 1, min(3, len(frames))).astype(int)
    fig = plt.figure(figsize=(12, 3.2 * len(picks) + 3.5))
    grid = fig.add_gridspec(len(picks) + 1, 2, height_ratios=[3.2] * len(picks) + [3.5])
    for row, i in enumerate(picks):
        ref = frames[i][2]
        pred = unpack_rgb(np.minimum(rendered[i], 0xFFFFFF).astype(np.uint32))
        for col, (img, title) in enumerate(((pred, f"rendered ({protocol}, {metric})"), (ref, "reference mask"))):
            ax = fig.add_subplot(grid[row, col])
            ax.imshow(img)
            ax.set_title(f"{title}, frame {i}", fontsize=9)
            ax.axis("off")
    ax = fig.add_subplot(grid[-1, :])
    items = sorted(scores["iou"].items(), key=lambda kv: kv[1])
    colors = [unpack_rgb(np.uint32(k)) / 255.0 for k, _ in items]
    ax.bar(range(len(items)), [v for _, v in items], color=colors, edgecolor="black", linewidth=0.4)
    ax.set_xticks(range(len(items)), [names.get(int(k), f"{int(k):06x}") for k, _ in items], rotation=70, fontsize=7)
    ax.set_ylabel("IoU")
    ax.set_ylim(0, 1)
    ax.set_title(f"per-object IoU ({protocol}), mIoU {100 * scores['miou']:.2f}%", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
