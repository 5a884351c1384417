"""How close a synthetic map is to a converged SLAM map, and what the method gets out of it: figures as JSON.

``python -m monovoc_ros.synthetic.quality [--n-gaussians N] [--stride 3] [--no-pipeline] ...``

On the keyframes ``0, stride, 2 stride, ...``, against the clean ground-truth masks:
- ``ground_truth``: each Gaussian labelled with its surface's true object, rendered through the Gaussians
  (``render_splat_labels``) and as discs of its centre (``render_point_labels``, the paper's protocol):
  the ceiling any labelling of this map can reach;
- ``rgb``: the map rendered with its own colors against the ray-cast RGB (PSNR, dB), i.e. how well the
  map would fit its keyframes photometrically;
- ``pipeline``: ``SemanticMapper`` over every keyframe, its labels rendered both ways, and the share of
  observed labelled Gaussians whose label is their surface's object;
- ``map``: what the generator made (counts, how many keyframes see each Gaussian, edge-bounded sizes).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from monovoc_ros.core.evaluation.evaluation import SegmentationEvaluator, render_point_labels, render_splat_labels
from monovoc_ros.core.evidence.palette import VOID_ID, pack_rgb
from monovoc_ros.synthetic.raycast import bounding_spheres
from monovoc_ros.synthetic.scene import FLOATER, SceneConfig, SyntheticScene, generate_scene
from monovoc_ros.synthetic.visibility import observed_views

POINT_SIZE = 0.05  # metres: the paper's disc size


def _names(scene: SyntheticScene) -> dict[int, str]:
    """Packed palette id -> "class#instance" (four walls, three books)."""
    return {int(pack_rgb(o.palette_rgb)): f"{o.class_name}#{o.instance_id}" for o in scene.objects}


def _summary(result: dict, names: dict[int, str]) -> dict:
    iou = {names.get(k, str(k)): round(float(v), 4) for k, v in result["iou"].items()}
    return {
        "miou": round(float(result["miou"]), 4),
        "mismatch_nonwhite": round(float(result["mismatch_nonwhite"]), 4),
        "min_iou": min(iou.values()) if iou else float("nan"),
        "iou": dict(sorted(iou.items(), key=lambda kv: kv[1])),
    }


def segmentation(scene: SyntheticScene, labels: np.ndarray, frames: list[int]) -> dict:
    """Per-Gaussian packed labels rendered by splatting and as discs, against the clean masks of ``frames``."""
    splat, disc = SegmentationEvaluator(), SegmentationEvaluator()
    g = scene.gaussians
    for i in frames:
        ref = pack_rgb(scene.clean_mask(i))
        splat.update(render_splat_labels(g, labels, scene.intrinsics, scene.poses[i]), ref)
        disc.update(render_point_labels(g.means, labels, scene.intrinsics, scene.poses[i], point_size=POINT_SIZE), ref)
    names = _names(scene)
    return {"splat": _summary(splat.result(), names), "disc": _summary(disc.result(), names)}


def rgb_psnr(scene: SyntheticScene, frames: list[int]) -> dict:
    """PSNR (dB) of the map rendered with its colors (black background) against the ray-cast RGB."""
    from monovoc_ros.core.raster import render  # deferred: pulls in the numba rasterizer

    psnr = []
    for i in frames:
        image = np.clip(render(scene.gaussians, scene.gaussians.colors, scene.intrinsics, scene.poses[i]).image, 0, 1)
        mse = float(np.mean((image - scene.rgb(i) / 255.0) ** 2))
        psnr.append(10 * np.log10(1.0 / max(mse, 1e-12)))
    return {"psnr_mean": round(float(np.mean(psnr)), 2), "psnr_min": round(float(np.min(psnr)), 2)}


def map_statistics(scene: SyntheticScene) -> dict:
    """Counts, keyframes seeing each surface Gaussian (at its surface point) and edge-bounded sizes."""
    g, go = scene.gaussians, scene.gaussian_object
    surface = go != FLOATER
    kinds, params = scene._kinds, scene._params
    normals = _surface_normals(scene)
    views, best_cos = observed_views(
        g.means[surface].astype(np.float64), normals[surface], scene.poses,
        scene.intrinsics, kinds, params, bounding_spheres(kinds, params), tolerance=0.02,
    )  # fmt: skip
    tangent = g.scales[surface][:, :2]
    interior = float(np.median(tangent.max(axis=1)))
    return {
        "gaussians": len(g),
        "floaters": int(np.sum(go == FLOATER)),
        "unlabelled_surface": int(np.sum(go == -2)),
        "views_per_gaussian": {
            "0": int(np.sum(views == 0)),
            "1": int(np.sum(views == 1)),
            "2": int(np.sum(views == 2)),
            "3+": int(np.sum(views >= 3)),
            "median": float(np.median(views)),
        },
        "grazing_only": int(np.sum((views > 0) & (best_cos < 0.2))),  # seen, but never within ~78 deg of its normal
        "median_largest_tangent_sigma_m": round(interior, 4),
        "edge_shrunk_fraction": round(float(np.mean(tangent.min(axis=1) < 0.5 * interior)), 4),
        "min_tangent_sigma_m": round(float(tangent.min()), 4),
    }


def _surface_normals(scene: SyntheticScene) -> np.ndarray:
    """The thin (third) axis of each Gaussian, turned to face out of its primitive."""
    from monovoc_ros.core.map.camera import quat_wxyz_to_matrix

    g = scene.gaussians
    n = quat_wxyz_to_matrix(g.quats)[:, :, 2].astype(np.float64)
    prim = scene.gaussian_primitive
    out = n.copy()
    for k in np.unique(prim[prim >= 0]):
        sel = prim == k
        p, h = g.means[sel].astype(np.float64), 1e-5
        f = scene.primitives[k].sdf
        grad = np.stack([(f(p + h * e) - f(p - h * e)) / (2 * h) for e in np.eye(3)], 1)
        out[sel] *= np.sign(np.sum(n[sel] * grad, axis=1, keepdims=True) + 1e-12)
    return out


def pipeline(scene: SyntheticScene, frames: list[int]) -> dict:
    """SemanticMapper over every keyframe; its labels evaluated like the ground truth's."""
    from monovoc_ros.core.mapping import MapperConfig, SemanticMapper

    start = time.perf_counter()
    mapper = SemanticMapper(scene.gaussians, MapperConfig())
    for i in range(len(scene)):
        mapper.integrate(scene.keyframe(i))
    result = mapper.result()
    seconds = time.perf_counter() - start
    truth = pack_rgb(scene.gaussian_palette_rgb())
    labelled = (scene.gaussian_object >= 0) & result.observed
    out = segmentation(scene, result.object_ids, frames)
    out["gaussian_accuracy"] = round(float(np.mean(result.object_ids[labelled] == truth[labelled])), 4)
    out["observed_labelled_gaussians"] = int(labelled.sum())
    out["unobserved_gaussians"] = int(np.sum(~result.observed))
    out["void_labelled_gaussians"] = int(np.sum(result.object_ids[labelled] == VOID_ID))
    out["seconds"] = round(seconds, 1)
    return out


def evaluate(config: SceneConfig, *, stride: int = 3, with_pipeline: bool = True) -> dict:
    start = time.perf_counter()
    scene = generate_scene(config)
    generation = time.perf_counter() - start
    frames = list(range(0, len(scene), stride))
    truth = pack_rgb(scene.gaussian_palette_rgb())
    out = {
        "config": {k: v for k, v in vars(config).items() if not k.startswith("_")},
        "frames": frames,
        "generation_seconds": round(generation, 2),
        "map": map_statistics(scene),
        "ground_truth": segmentation(scene, truth, frames),
        "rgb": rgb_psnr(scene, frames),
    }
    if with_pipeline:
        out["pipeline"] = pipeline(scene, frames)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-gaussians", type=int, default=SceneConfig.n_gaussians)
    ap.add_argument("--n-keyframes", type=int, default=SceneConfig.n_keyframes)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stride", type=int, default=3, help="evaluate keyframes 0, stride, 2 stride, ...")
    ap.add_argument("--no-pipeline", action="store_true", help="skip the SemanticMapper run")
    ap.add_argument("--uniform", action="store_true", help="the old map: fixed sizes, no edge densification")
    ap.add_argument("--all-surfaces", action="store_true", help="Gaussians on unobserved surfaces too")
    ap.add_argument("--out", help="also write the JSON here")
    a = ap.parse_args(argv)
    config = SceneConfig(
        seed=a.seed, n_gaussians=a.n_gaussians, n_keyframes=a.n_keyframes, edge_adaptive=not a.uniform,
        observed_only=not a.all_surfaces,
    )  # fmt: skip
    out = evaluate(config, stride=a.stride, with_pipeline=not a.no_pipeline)
    text = json.dumps(out, indent=1, default=float)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
