"""The object index: ONE language embedding per object, kept up to date as the map grows (METHOD 5).

An object's embedding is the normalized mean of the image embeddings of its best views (``views``),
cropped with a soft mask by default, optionally mixed with the embedding of its attribute description
("a blue chair, 0.97 m tall": the dominant color name of its view pixels, its 3D size and its height
above the floor from the map). A text query embeds the text and ranks objects by cosine similarity.

Incremental: ``refresh`` re-embeds only objects whose view set changed since they were last embedded
(and, among those, only the views not embedded before), and re-embeds a description only when its text
changed. A description's numbers are re-quoted only when the object's size or height moved by more than
QUOTE_TOLERANCE from those it quotes (the records keep the exact ones): a SLAM map update shifts every
object by millimetres and its floor by a few centimetres, which re-wrote half the descriptions of a 1M
map every 2 s (~0.1 of a core in the text encoder). ``max_objects`` bounds the image-embedding work of one
call so a node can refresh after every keyframe. Queries read an immutable snapshot swapped in atomically,
so they never wait for a refresh.

Frames: sizes, heights and the floor (a low percentile of the Gaussians' height) are measured along
``up_axis``. The synthetic scene and REP-103 maps have z up ("+z"). Replica's traj.txt world is
keyframe 0's OpenCV camera frame (x right, y down, z forward): only roughly "-y" up, as level as that
camera was (office_0's looked ~45 degrees down). The default "auto" estimates up from the keyframe poses
and the map's horizontal surfaces (``upright``): +z within 0.001 on the synthetic room, and the
floor's normal on office_0. Centroids and boxes in the records stay in the map frame.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass

import numpy as np

from monovoc_ros.core.evidence.palette import format_object_id, parse_object_id
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.object_geometry import ObjectSummary
from monovoc_ros.core.segments.object_labels import GIVEN, GUESS, SEGMENTS, ObjectLabel, resolve
from monovoc_ros.embed.arrays import l2_normalize
from monovoc_ros.embed.attributes import best_class_name, combine, describe, dominant_color_name
from monovoc_ros.embed.crops import crop_object
from monovoc_ros.embed.model_store import ModelMissingError
from monovoc_ros.objects.labels import head_noun, noun
from monovoc_ros.objects.records import ObjectRecord, QueryError, QueryResult
from monovoc_ros.objects.upright import UprightGeometry, axis_vector, camera_up, estimate_up, upright_geometry
from monovoc_ros.objects.views import ObjectView, ObjectViews, ViewConfig

CROP_MODES = ("soft", "hard")
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z", "auto")
TEXT_CACHE_SIZE = 256  # query texts whose embeddings are kept
# Objects embedded per refresh call by default in a live node: ~3 views x 18 ms each on 2 cores, so
# ~0.45 s of work per call, short enough that keyframes and map updates keep flowing.
LIVE_OBJECTS_PER_REFRESH = 8
# New views embedded between two looks at refresh's should_stop (~70 ms on 2 cores, several times that on
# the niced indexing thread of a busy node): a stopping node waits for one chunk, not for a whole call.
EMBED_CHUNK_VIEWS = 4
# A description keeps the size and height it quotes while each current value stays within this share of it (or
# QUOTE_MIN_M): its text, and so its embedding, does not move with millimetres of SLAM map updates.
QUOTE_TOLERANCE = 0.1
QUOTE_MIN_M = 0.01


@dataclass
class IndexConfig:
    crop_mode: str = "soft"  # "soft" (context dimmed, the paper's better choice) or "hard" (object only)
    context: float = 0.15  # crop margin around the object's box (fraction of its size)
    dim: float = 0.35  # soft mode: how far the context is blended toward grey
    views_per_object: int = 3
    # Share of the attribute description in the object's embedding; 0 = image embedding only.
    # Measured with the conse backend, soft crops, top-1 / top-3 (config/queries; objects without given
    # labels): synthetic room (30 queries) image only 0.33 / 0.47, with the description at 0.3 0.33 / 0.57,
    # at 0.5 0.27 / 0.57; Replica office_0 (24 queries) 0.33 / 0.33 at 0, 0.3 and 0.5. Naming the object by
    # its best ImageNet class in the description instead was worse (synthetic 0.27 / 0.40 at 0.5): a
    # wrong guess is repeated, so by default the description carries the attributes only.
    description_weight: float = 0.3
    # The noun of the description of an object without a given label: a fixed word ("object": attributes
    # only, the image embedding carries the class) or "imagenet" (its best ImageNet class).
    unlabeled_noun: str = "object"
    # A text whose head noun is an object's label (given or a segmenter's; "the dark blue chairs" and "chair")
    # ranks it up by label_weight x the label's confidence (segmenter: the share of the object's class evidence
    # naming it). ConSE's cosines for one text spread over ~0.3, so 0.5 puts unanimously named objects first
    # and lets a contested name (a table called "chair" in some frames, "dining table" in others) fall behind
    # them; the embedding orders objects of equal confidence (attributes: "the gray sofa"). 0 = embedding only.
    # office_0 with YOLOv5s-seg's labels (bench_camera_to_map): top-1 0.67 at 0, 0.89 at 0.5 (docs/results.md).
    label_weight: float = 0.5
    labels: dict[int, str] | None = None  # object id -> class name (e.g. from labels.json)
    min_gaussians: int = 10  # objects with fewer Gaussians are not listed (specks, mislabeled floaters)
    up_axis: str = "auto"  # see the module docstring; "+z" for REP-103 maps known to be level
    floor_percentile: float = 1.0  # the floor height: this percentile of all Gaussians' heights
    default_top_k: int = 5  # what top_k = 0 means
    max_query_chars: int = 1000  # longer query texts are truncated (the text encoder reads 256 tokens anyway), longer
    # questions refused (objects.questions)
    min_view_pixels: int = 20
    max_view_side: int = 448

    def __post_init__(self) -> None:
        if self.crop_mode not in CROP_MODES:
            raise ValueError(f"crop_mode must be one of {CROP_MODES}, got {self.crop_mode!r}")
        if not 0.0 <= self.description_weight <= 1.0:
            raise ValueError(f"description_weight must be in [0, 1], got {self.description_weight}")
        if not 0.0 <= self.label_weight <= 2.0:
            raise ValueError(f"label_weight must be in [0, 2], got {self.label_weight}")
        if self.up_axis not in UP_AXES:
            raise ValueError(f"up_axis must be one of {UP_AXES}, got {self.up_axis!r}")
        if not 0.0 <= self.floor_percentile <= 100.0:
            raise ValueError(f"floor_percentile must be in [0, 100], got {self.floor_percentile}")
        if int(self.default_top_k) < 1:
            raise ValueError(f"default_top_k must be >= 1, got {self.default_top_k}")
        if int(self.max_query_chars) < 1:
            raise ValueError(f"max_query_chars must be >= 1, got {self.max_query_chars}")
        if not str(self.unlabeled_noun).strip():
            raise ValueError("unlabeled_noun must be 'imagenet' or a word such as 'object'")
        if int(self.min_gaussians) < 1:
            raise ValueError(f"min_gaussians must be >= 1, got {self.min_gaussians}")
        if self.labels is not None:
            # An unnamed labels.json color (class name "") names nothing.
            self.labels = {parse_object_id(k): str(v) for k, v in self.labels.items() if str(v)}
        self.view_config()  # validates the view fields

    def view_config(self) -> ViewConfig:
        return ViewConfig(self.views_per_object, self.context, self.min_view_pixels, self.max_view_side)

    def to_dict(self) -> dict:
        """JSON-able (labels keyed by #rrggbb)."""
        d = asdict(self)
        d["labels"] = None if self.labels is None else {format_object_id(k): v for k, v in self.labels.items()}
        return d

    @classmethod
    def from_dict(cls, data: Mapping) -> IndexConfig:
        known = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in data.items() if k in known})


@dataclass
class RefreshReport:
    embedded_objects: int = 0  # objects whose image embedding was (re)computed
    embedded_views: int = 0  # views newly run through the image encoder
    embedded_descriptions: int = 0  # description texts newly run through the text encoder
    pending: int = 0  # dirty objects left for the next call (max_objects)
    listed: int = 0  # objects in the index after the call
    seconds: float = 0.0


def backend_identity(backend) -> dict:
    """What makes two backends' embeddings comparable: name, dimension and the options that change them."""
    info = {"name": str(getattr(backend, "name", type(backend).__name__)), "dim": int(backend.dim)}
    for option in ("top_k", "fit"):
        if hasattr(backend, option):
            info[option] = getattr(backend, option)
    return info


def model_name(info: Mapping) -> str:
    """``conse(fit=pad,top_k=10)``: a short string naming the embedding model and its options."""
    options = ",".join(f"{k}={info[k]}" for k in sorted(info) if k not in ("name", "dim", "model_dir"))
    return f"{info['name']}({options})" if options else str(info["name"])


class ObjectIndex:
    """Object views, records and embeddings of one map; see the module docstring.

    ``backend``: an embedding backend, or a zero-argument callable that creates one on first use (so a
    node can start, and collect views, before the models are there; errors surface per call).
    """

    def __init__(self, backend: object, config: IndexConfig | None = None) -> None:
        self.config = config or IndexConfig()
        self.views = ObjectViews(self.config.view_config())
        self._backend_source = backend
        self._backend = None if callable(backend) and not hasattr(backend, "embed_texts") else backend
        self._backend_lock = threading.Lock()
        self._refresh_lock = threading.Lock()
        self._lock = threading.Lock()
        # Query texts embedded lately (a robot asks the same few things again and again): a hit skips the text
        # encoder, which shares the CPU with the image encoder and the rasterizer while the node maps.
        self._query_cache: OrderedDict[str, np.ndarray] = OrderedDict()
        # Immutable snapshot for queries: (records in id order, (M, d) embedding matrix).
        self._snapshot: tuple[tuple[ObjectRecord, ...], np.ndarray] = ((), np.zeros((0, 0), np.float32))
        self._summaries: dict[int, ObjectSummary] = {}
        self._observations: dict[int, int] = {}
        # object id -> the segmenter's class (refresh(mapper) or refresh(segment_labels=...))
        self.segment_labels: dict[int, str] = {}
        self.segment_confidence: dict[int, float] = {}  # object id -> its segment label's confidence
        self._floor = 0.0
        self._upright: dict[int, tuple[np.ndarray, float]] = {}  # id -> (extent with height last, height)
        # What _floor and _upright come from, kept for the next refresh: the upright centres (12 bytes per Gaussian)
        # and the shaping ids of the map in use.
        self._upright_geometry: UprightGeometry | None = None
        self._up_sum = np.zeros(3)  # sum of the keyframes' camera up directions (up_axis "auto")
        # The latest keyframe's camera pose (4, 4) cam_to_world: the robot's viewpoint for spatial queries.
        self.viewpoint: np.ndarray | None = None
        self._up: np.ndarray | None = None  # "auto": refined by the map's horizontal surfaces
        self._up_key: int | None = None
        self._geometry_key: tuple | None = None
        self.object_ids: np.ndarray | None = None  # (N,) per-Gaussian ids of the last refresh's result
        self.gaussians: GaussianMap | None = None
        self._embedded_version: dict[int, int] = {}
        self._image_emb: dict[int, np.ndarray] = {}
        self._color: dict[int, str] = {}
        self._num_views: dict[int, int] = {}
        self._guess: dict[int, ObjectLabel] = {}  # the model's best class, per embedded object
        # Names (given or segments) of records restored from a database: a restart without labels_file keeps them.
        self._restored_label: dict[int, ObjectLabel] = {}
        self._text_cache: dict[str, np.ndarray] = {}
        # object id -> (its image embedding, its description, the description's weight, their combination) of the
        # last _publish: most objects change neither between two refreshes (1M Gaussians, 170 objects: combining
        # took 9% of a refresh).
        self._combined: dict[int, tuple[np.ndarray, str, float, np.ndarray]] = {}
        # object id -> (extent with height last, height above the floor) its description quotes (`_quoted_geometry`)
        self._quoted: dict[int, tuple[np.ndarray, float]] = {}
        self._restored_backend_info: dict | None = None

    # ------------------------------------------------------------------ backend

    @property
    def backend(self):
        """The embedding backend, created on first use; raises ModelMissingError when models are missing."""
        if self._backend is None:
            with self._backend_lock:
                if self._backend is None:
                    self._backend = self._backend_source()
        return self._backend

    @property
    def backend_loaded(self) -> bool:
        return self._backend is not None

    @property
    def backend_info(self) -> dict | None:
        """The identity of the backend the embeddings come from (``backend_identity``); before the
        backend is loaded, the one restored from a database, else None."""
        if self._backend is not None:
            info = backend_identity(self._backend)
            model_dir = getattr(self._backend, "model_dir", None)
            if model_dir is not None:
                info["model_dir"] = str(model_dir)
            return info
        return self._restored_backend_info

    def view_key(self, info: Mapping) -> tuple:
        """The key of a view's cached image embedding: crop settings and the model's name."""
        c = self.config
        return (c.crop_mode, float(c.context), float(c.dim), model_name(info))

    # ------------------------------------------------------------------ views

    def observe(self, keyframe: Keyframe, palette_ids: np.ndarray | None = None) -> list[int]:
        """Offers a keyframe's object views (cheap; see ObjectViews.observe)."""
        self._up_sum += camera_up(keyframe.cam_to_world)
        self.viewpoint = np.array(keyframe.cam_to_world, np.float64)
        return self.views.observe(keyframe, palette_ids)

    def keyframe_listener(self, keyframe: Keyframe, mapper) -> None:
        """``fn(keyframe, mapper)`` for the node's / offline mapper's keyframe hook: observes the keyframe
        with the palette seen so far (this keyframe included)."""
        self.observe(keyframe, mapper.palette_builder.build().ids)

    def up_vector(self) -> np.ndarray:
        """The map's up direction: the configured axis, or for "auto" the estimate of the last refresh
        (``upright.estimate_up``), else the mean camera up seen so far (+z before any keyframe)."""
        if self.config.up_axis != "auto":
            return axis_vector(self.config.up_axis)
        if self._up is not None:
            return self._up
        norm = np.linalg.norm(self._up_sum)
        return self._up_sum / norm if norm > 1e-9 else axis_vector("+z")

    # ------------------------------------------------------------------ refresh

    def pending(self) -> int:
        """Listed objects whose embedding is missing or stale."""
        versions = self.views.versions()
        return sum(1 for oid in self._listable(versions) if versions.get(oid) != self._embedded_version.get(oid))

    def _listable(self, versions: Mapping[int, int]) -> list[int]:
        return [
            oid
            for oid, s in self._summaries.items()
            if s.num_gaussians >= self.config.min_gaussians and versions.get(oid, 0) > 0
        ]

    def refresh(
        self,
        mapper=None,
        *,
        gaussians: GaussianMap | None = None,
        result=None,
        segment_labels: Mapping[int, str] | None = None,
        label_confidence: Mapping[int, float] | None = None,
        max_objects: int | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> RefreshReport:
        """Updates geometry from ``mapper`` (or ``gaussians`` + ``result``), re-embeds dirty objects (at
        most ``max_objects`` of them, never-embedded ones and large ones first) and publishes the new
        records. Without geometry arguments only embeddings are brought up to date. ``segment_labels`` and
        ``label_confidence`` (the mapper's ``object_labels()`` and ``object_label_confidence()``, taken with
        ``result``): the segmenter's class names and how sure they are, which ``refresh(mapper)`` reads itself.
        ``should_stop`` (a live node's stop) is asked between chunks of EMBED_CHUNK_VIEWS views: a stopping node
        does not wait for a whole batch; objects not reached stay pending, views already embedded keep their
        embeddings. Without it, the batch goes to the image encoder at once."""
        start = time.perf_counter()
        report = RefreshReport()
        with self._refresh_lock:
            if mapper is not None:
                gaussians, result = mapper.gaussians, mapper.result()
                self.segment_labels = mapper.object_labels()
                self.segment_confidence = mapper.object_label_confidence()
            elif segment_labels is not None:
                self.segment_labels = dict(segment_labels)
                self.segment_confidence = dict(label_confidence or {})
            if (gaussians is None) != (result is None):
                raise ValueError("refresh needs both gaussians and result (or a mapper)")
            if gaussians is not None:
                self._update_geometry(gaussians, result)
            versions = self.views.versions()
            listed = self._listable(versions)
            dirty = [oid for oid in listed if versions.get(oid) != self._embedded_version.get(oid)]
            dirty.sort(key=lambda oid: (oid in self._image_emb, -self._summaries[oid].num_gaussians, oid))
            batch = dirty if max_objects is None else dirty[: max(0, int(max_objects))]
            if batch:
                report.embedded_objects, report.embedded_views = self._embed_objects(
                    batch, versions, self.backend, should_stop
                )
            report.pending = len(dirty) - report.embedded_objects
            ready = [oid for oid in listed if oid in self._image_emb]
            if ready:
                report.embedded_descriptions = self._publish(ready, self.backend)
            else:
                self._swap((), np.zeros((0, 0), np.float32))
            report.listed = len(ready)
        report.seconds = time.perf_counter() - start
        return report

    def _update_geometry(self, gaussians: GaussianMap, result) -> None:
        key = (id(gaussians), id(result))
        if key == self._geometry_key:
            return
        # The result's one geometry (core.object_geometry): the objects topic and its markers report the same.
        geometry = result.objects(gaussians)
        self._summaries = {s.id: s for s in geometry.objects}
        if self.config.up_axis == "auto" and self._up_key != id(gaussians):
            self._up = None  # re-estimate from the camera hint, which improves with every keyframe
            self._up = estimate_up(gaussians, self.up_vector())
            self._up_key = id(gaussians)
        self._upright_geometry = upright_geometry(
            gaussians, geometry, self.up_vector(), self.config.floor_percentile, self._upright_geometry
        )
        self._floor, self._upright = self._upright_geometry.floor, self._upright_geometry.extents
        palette = result.palette
        self._observations = dict(zip(palette.ids.tolist(), palette.mask_counts.tolist(), strict=True))
        self.object_ids = result.object_ids
        self.gaussians = gaussians
        self._geometry_key = key

    def _embed_objects(
        self, batch: list[int], versions: Mapping[int, int], backend, should_stop: Callable[[], bool] | None
    ) -> tuple[int, int]:
        """Embeds `batch`'s objects in order (with `should_stop`: in chunks of about EMBED_CHUNK_VIEWS new views,
        until it says stop); returns (objects embedded, views newly embedded)."""
        key = self.view_key(backend_identity(backend))
        chunk_views = EMBED_CHUNK_VIEWS if should_stop is not None else math.inf
        objects = views_done = 0
        chunk: dict[int, list[ObjectView]] = {}
        new_views = 0
        for n, oid in enumerate(batch):
            chunk[oid] = views = self.views.views(oid)
            new_views += sum(key not in v.embeddings for v in views)
            if new_views < chunk_views and n + 1 < len(batch):
                continue
            views_done += self._embed_chunk(chunk, key, versions, backend)
            objects += len(chunk)
            chunk, new_views = {}, 0
            if should_stop is not None and should_stop():
                break
        return objects, views_done

    def _embed_chunk(
        self, per_object: dict[int, list[ObjectView]], key: tuple, versions: Mapping[int, int], backend
    ) -> int:
        c = self.config
        todo = [v for views in per_object.values() for v in views if key not in v.embeddings]
        if todo:
            crops = [crop_object(v.rgb, v.mask, c.crop_mode, context=c.context, dim=c.dim) for v in todo]
            for view, emb in zip(todo, backend.embed_images(crops), strict=True):
                view.embeddings[key] = emb
        for oid, views in per_object.items():
            self._image_emb[oid] = l2_normalize(np.mean([v.embeddings[key] for v in views], axis=0))
            self._color[oid] = dominant_color_name(np.concatenate([v.pixels() for v in views]))
            self._num_views[oid] = len(views)
            self._guess.pop(oid, None)
            self._embedded_version[oid] = versions[oid]
        return len(todo)

    def _label(self, oid: int, backend) -> ObjectLabel:
        """The one rule (core.segments.object_labels.resolve), with the model's guess last."""
        label = resolve(
            oid, self.config.labels or {}, self.segment_labels, self._restored_label, self.segment_confidence
        )
        if label is not None:
            return label
        if oid not in self._guess:
            self._guess[oid] = ObjectLabel(best_class_name(self._image_emb[oid], backend), GUESS)
        return self._guess[oid]

    def labels(self) -> dict[int, ObjectLabel]:
        """Object id -> label of the queryable objects (what the answers and objects.db carry)."""
        return {r.id: ObjectLabel(r.label, r.label_source, r.label_confidence) for r in self._snapshot[0] if r.label}

    def describe(self, oid: int, label: str, quoted: tuple[np.ndarray, float] | None = None) -> str:
        """The attribute description of a listed, embedded object under ``label``, quoting its current size and
        height above the floor, or ``quoted`` ones (`_quoted_geometry`)."""
        extent, height = self._upright[oid] if quoted is None else quoted
        return describe(
            noun(label) or "object", color=self._color[oid], extent=extent, height_above_floor=height, up_axis=2
        )

    def _quoted_geometry(self, oid: int) -> tuple[np.ndarray, float]:
        """The size and height an object's description quotes: those it quoted last while every current value is
        within QUOTE_TOLERANCE (or QUOTE_MIN_M) of them, else the current ones."""
        extent, height = self._upright[oid]
        last = self._quoted.get(oid)
        if last is not None:
            was = np.append(last[0], last[1])
            now = np.append(extent, height)
            if np.all(np.abs(now - was) <= np.maximum(QUOTE_TOLERANCE * np.abs(was), QUOTE_MIN_M)):
                return last
        return extent, height

    def _publish(self, ready: list[int], backend) -> int:
        c = self.config
        now = time.time()
        rows = []
        quoted = {}
        for oid in sorted(ready):
            label = self._label(oid, backend)
            subject = c.unlabeled_noun if label.is_guess and c.unlabeled_noun != "imagenet" else label.name
            quoted[oid] = self._quoted_geometry(oid)
            rows.append((oid, label, self.describe(oid, subject, quoted[oid])))
        self._quoted = quoted
        embedded = 0
        if c.description_weight > 0:
            new = sorted({d for *_, d in rows if d not in self._text_cache})
            if new:
                for text, emb in zip(new, backend.embed_texts(new), strict=True):
                    self._text_cache[text] = emb
                embedded = len(new)
            in_use = {d for *_, d in rows}
            for text in [t for t in self._text_cache if t not in in_use]:
                del self._text_cache[text]
        previous = {r.id: r for r in self._snapshot[0]}
        records = []
        combined: dict[int, tuple[np.ndarray, str, float, np.ndarray]] = {}
        for oid, label, description in rows:
            s = self._summaries[oid]
            image = self._image_emb[oid]
            final = image
            if c.description_weight > 0:
                key = (image, description, c.description_weight)
                cached = self._combined.get(oid)
                if cached is not None and cached[0] is image and cached[1:] == key[1:]:
                    final = cached[3]
                else:
                    final = combine(image, self._text_cache[description], c.description_weight)
                combined[oid] = (*key, final)
            record = ObjectRecord(
                id=oid,
                label=label.name,
                label_source=label.source,
                label_confidence=float(label.confidence),
                description=description,
                color_name=self._color[oid],
                centroid=np.asarray(s.centroid, np.float64),
                bbox_min=np.asarray(s.bbox_min, np.float64),
                bbox_max=np.asarray(s.bbox_max, np.float64),
                num_gaussians=int(s.num_gaussians),
                num_observations=int(self._observations.get(oid, self.views.observations(oid))),
                embedding=final,
                image_embedding=image,
                updated_unix=now,
                num_views=self._num_views.get(oid, 0),
                upright_extent=np.asarray(self._upright[oid][0], np.float64),
                height_above_floor=float(self._upright[oid][1]),
            )
            old = previous.get(oid)
            if old is not None and _same_record(old, record):
                record.updated_unix = old.updated_unix
            records.append(record)
        self._combined = combined
        self._swap(tuple(records), np.stack([r.embedding for r in records]).astype(np.float32))
        return embedded

    def _swap(self, records: tuple[ObjectRecord, ...], matrix: np.ndarray) -> None:
        with self._lock:
            self._snapshot = (records, matrix)

    # ------------------------------------------------------------------ reading

    def records(self) -> list[ObjectRecord]:
        """Queryable objects (listed and embedded), by id."""
        return list(self._snapshot[0])

    def record(self, object_id: int) -> ObjectRecord | None:
        return next((r for r in self._snapshot[0] if r.id == int(object_id)), None)

    def __len__(self) -> int:
        return len(self._snapshot[0])

    def embedding_matrix(self) -> tuple[list[int], np.ndarray]:
        """Object ids (in record order) and their (M, d) embeddings, for batch ranking."""
        records, matrix = self._snapshot
        return [r.id for r in records], matrix

    def query(self, text: str, top_k: int = 0, min_score: float = -1.0) -> QueryResult:
        """Objects ranked by cosine similarity of their embedding to the text's, best first; an object whose
        label the text names (its head noun) ranks up by ``label_weight`` x the label's confidence. The scores
        returned, and ``min_score``, are the cosine similarities.

        ``top_k`` 0 means ``config.default_top_k``; more than there are objects returns them all.
        ``min_score`` drops weaker matches (-1 keeps everything). Raises QueryError for empty text, bad
        arguments or missing models; an index without objects answers with no matches and a message.
        """
        if not isinstance(text, str):
            raise QueryError(f"query text must be a string, got {type(text).__name__}")
        cleaned = " ".join(text.split())
        if not cleaned:
            raise QueryError("empty query: give a text to search for, e.g. 'a chair'")
        truncation = ""
        if len(cleaned) > self.config.max_query_chars:
            truncation = f"query truncated from {len(cleaned)} to {self.config.max_query_chars} characters"
            cleaned = cleaned[: self.config.max_query_chars]
        notes = [truncation] if truncation else []
        try:
            top_k = int(top_k)
            min_score = float(min_score)
        except (TypeError, ValueError) as exc:
            raise QueryError(f"top_k must be an integer and min_score a number ({exc})") from None
        if top_k < 0:
            raise QueryError(f"top_k must be >= 0 (0 = default {self.config.default_top_k}), got {top_k}")
        if math.isnan(min_score):
            raise QueryError("min_score is NaN")
        records, matrix = self._snapshot
        if not records:
            waiting = self.pending()
            why = f"{self.views.keyframes} keyframes seen" + (f", {waiting} objects being embedded" if waiting else "")
            return QueryResult(cleaned, [], "; ".join([f"no objects in the map yet ({why})", *notes]), 0, truncation)
        with self._lock:
            query = self._query_cache.get(cleaned)
            if query is not None:
                self._query_cache.move_to_end(cleaned)  # least recently used goes first
        if query is None:
            try:
                query = self.backend.embed_texts([cleaned])[0]
            except ModelMissingError as exc:
                raise QueryError(f"cannot embed the query: {exc}") from exc
            with self._lock:
                self._query_cache[cleaned] = query
                while len(self._query_cache) > TEXT_CACHE_SIZE:
                    self._query_cache.popitem(last=False)
        if query.shape[0] != matrix.shape[1]:
            raise QueryError(
                f"the query embedding has dimension {query.shape[0]} but the objects have {matrix.shape[1]}: "
                "the index was built with another embedding backend"
            )
        scores = matrix @ query
        named = label_match(records, cleaned)
        order = np.argsort(-(scores + self.config.label_weight * named), kind="stable")
        k = min(top_k or self.config.default_top_k, len(records))
        kept = [int(i) for i in order if scores[i] >= min_score][:k]
        matches = [(records[i], float(scores[i])) for i in kept]
        below = "" if len(kept) == k else f" (others below min_score {min_score:g})"
        message = f"{len(matches)} of {len(records)} objects{below}"
        if self.config.label_weight > 0 and named.any():
            notes.append(f"{np.count_nonzero(named)} labelled {head_noun(cleaned)!r} ranked by label confidence")
        return QueryResult(cleaned, matches, "; ".join([message, *notes]), len(records), truncation)

    # ------------------------------------------------------------------ persistence support

    def restore(
        self,
        records: list[ObjectRecord],
        views: list[ObjectView],
        *,
        observations: dict[int, int] | None = None,
        object_ids: np.ndarray | None = None,
        floor: float = 0.0,
        up: np.ndarray | None = None,
        viewpoint: np.ndarray | None = None,
        backend_info: dict | None = None,
        embeddings_valid: bool = True,
    ) -> None:
        """Puts saved state back (the object database's load): records become queryable at once and
        count as embedded for their restored views, so nothing is re-embedded until views change.

        ``embeddings_valid=False`` (the saved embeddings come from another backend) keeps geometry,
        colors and views but no embeddings: the next ``refresh()`` re-embeds every object."""
        with self._refresh_lock:
            self._restored_backend_info = backend_info
            self.views.restore(views, observations)
            versions = self.views.versions()
            self._summaries = {
                r.id: ObjectSummary(r.id, r.rgb, r.num_gaussians, r.centroid, r.bbox_min, r.bbox_max) for r in records
            }
            self._observations = {r.id: r.num_observations for r in records}
            self._upright = {r.id: (np.asarray(r.upright_extent, np.float64), r.height_above_floor) for r in records}
            self._upright_geometry = None  # the restored sizes are the records': the next refresh computes them all
            self._combined.clear()
            if up is not None:
                self._up = np.asarray(up, np.float64)
            if viewpoint is not None:
                self.viewpoint = np.asarray(viewpoint, np.float64).reshape(4, 4)
            self._geometry_key = None
            self._floor = float(floor)
            self.object_ids = object_ids
            self._image_emb.clear()
            self._embedded_version.clear()
            self._guess.clear()
            self._restored_label.clear()
            for r in records:
                self._color[r.id] = r.color_name
                self._num_views[r.id] = r.num_views
                label = ObjectLabel.stored(r.label, r.label_source, r.label_confidence)
                if label is not None and label.source in (GIVEN, SEGMENTS):
                    self._restored_label[r.id] = label
                if embeddings_valid:
                    self._image_emb[r.id] = r.image_embedding
                    if label is not None and label.is_guess:  # the guess of these embeddings
                        self._guess[r.id] = label
                    self._embedded_version[r.id] = versions.get(r.id, 0)
            ordered = tuple(sorted(records, key=lambda r: r.id)) if embeddings_valid else ()
            matrix = np.stack([r.embedding for r in ordered]).astype(np.float32) if ordered else np.zeros((0, 0))
            self._swap(ordered, matrix.astype(np.float32))

    def floor_height(self) -> float:
        return self._floor


def label_match(records: tuple[ObjectRecord, ...], text: str) -> np.ndarray:
    """(M,) float32 per record: its label's confidence where the label (given or a segmenter's, never the
    model's guess) has the text's head noun as its own, else 0."""
    head = head_noun(text)
    return np.array([r.label_confidence if r.labelled(head) else 0.0 for r in records], np.float32)


def _same_record(a: ObjectRecord, b: ObjectRecord) -> bool:
    return (
        a.label == b.label
        and a.label_source == b.label_source
        and a.label_confidence == b.label_confidence
        and a.description == b.description
        and a.num_gaussians == b.num_gaussians
        and a.num_observations == b.num_observations
        and np.array_equal(a.centroid, b.centroid)
        and np.array_equal(a.bbox_min, b.bbox_min)
        and np.array_equal(a.bbox_max, b.bbox_max)
        and np.array_equal(a.embedding, b.embedding)
    )


def lazy_backend(name: str = "conse", **options) -> Callable[[], object]:
    """A zero-argument factory for ``ObjectIndex(backend=...)`` that loads the backend on first use."""

    def load():
        from monovoc_ros.embed.backend import load_backend

        return load_backend(name, **options)

    load.backend_name = name  # type: ignore[attr-defined]
    load.backend_options = dict(options)  # type: ignore[attr-defined]
    return load


__all__ = [
    "CROP_MODES",
    "UP_AXES",
    "IndexConfig",
    "ObjectIndex",
    "QueryError",
    "QueryResult",
    "RefreshReport",
    "backend_identity",
    "lazy_backend",
    "model_name",
]
