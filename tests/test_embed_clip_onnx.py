"""The clip_onnx backend's mechanics with tiny randomly initialised encoders exported to ONNX here.

No CLIP weights can be had offline, so this checks what the backend itself is responsible for: the
export helper, preprocessing (fit, scale, mean/std, NCHW), token ids (sot/eot/pad/truncation),
batching, normalisation, and clear errors on a bad model directory.
"""

import json
import shutil

import numpy as np
import pytest
import torch
from tokenizers import Tokenizer, models, pre_tokenizers

from monovoc_ros.embed import EmbeddingBackend, ModelMissingError, load_backend
from monovoc_ros.embed.clip_export import export_clip_onnx
from monovoc_ros.embed.clip_onnx import CONFIG_JSON, TEXTUAL_ONNX, ClipConfig, ClipOnnxBackend

VOCAB = {"<pad>": 0, "<unk>": 1, "<sot>": 2, "<eot>": 3, "a": 4, "photo": 5, "of": 6, "red": 7, "chair": 8, "lamp": 9}
CONFIG = {
    "image_size": 32,
    "image_mean": [0.5, 0.4, 0.3],
    "image_std": [0.2, 0.25, 0.3],
    "image_fit": "center_crop",
    "context_length": 8,
    "sot_id": 2,
    "eot_id": 3,
    "pad_id": 0,
}


class TinyClip(torch.nn.Module):
    def __init__(self, image_dim: int = 16, text_dim: int = 16) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 8, 3, stride=2, padding=1)
        self.image_proj = torch.nn.Linear(8, image_dim)
        self.embed = torch.nn.Embedding(len(VOCAB), 12)
        self.text_proj = torch.nn.Linear(12, text_dim)

    def encode_image(self, images: torch.Tensor) -> torch.Tensor:
        return self.image_proj(torch.relu(self.conv(images)).mean(dim=(2, 3)))

    def encode_text(self, token_ids: torch.Tensor) -> torch.Tensor:
        return self.text_proj(self.embed(token_ids).mean(dim=1))


def _tokenizer_json(path):
    tokenizer = Tokenizer(models.WordLevel(VOCAB, unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer.save(str(path))
    return path


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    model = TinyClip()
    out = export_clip_onnx(model, root / "model", _tokenizer_json(root / "tok.json"), CONFIG)
    return model, out


@pytest.fixture(scope="module")
def backend(exported):
    return load_backend("clip_onnx", model_dir=exported[1], threads=1)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_export_writes_the_documented_directory(exported, backend):
    _, out = exported
    names = sorted(p.name for p in out.iterdir())
    assert names == ["clip_config.json", "textual.onnx", "tokenizer.json", "visual.onnx"]
    assert ClipConfig.from_dict(json.loads((out / CONFIG_JSON).read_text())) == ClipConfig.from_dict(CONFIG)
    assert isinstance(backend, EmbeddingBackend)
    assert backend.name == "clip_onnx" and backend.dim == 16


def test_token_ids_follow_sot_eot_pad_rules(backend):
    ids = backend.token_ids(["A  red CHAIR", "a zebra", "a photo of a red chair a lamp", ""])
    np.testing.assert_array_equal(
        ids,
        [
            [2, 4, 7, 8, 3, 0, 0, 0],  # lower-cased, whitespace collapsed
            [2, 4, 1, 3, 0, 0, 0, 0],  # unknown word
            [2, 4, 5, 6, 4, 7, 8, 3],  # cut to context_length, eot kept last
            [2, 3, 0, 0, 0, 0, 0, 0],
        ],
    )
    assert ids.dtype == np.int64


def test_embeddings_match_the_torch_model(exported, backend):
    model, _ = exported
    rng = np.random.default_rng(3)
    crops = [rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for _ in range(3)]
    # Independent preprocessing: a 32x32 crop needs no resize; scale to [0, 1], normalise, NCHW.
    pixels = (np.stack(crops) / 255.0 - np.array(CONFIG["image_mean"])) / np.array(CONFIG["image_std"])
    with torch.no_grad():
        expected_images = model.encode_image(torch.tensor(pixels.transpose(0, 3, 1, 2), dtype=torch.float32)).numpy()
        expected_texts = model.encode_text(torch.tensor([[2, 4, 7, 8, 3, 0, 0, 0], [2, 9, 3, 0, 0, 0, 0, 0]])).numpy()
    np.testing.assert_allclose(backend.embed_images(crops), _unit(expected_images), atol=1e-5)
    np.testing.assert_allclose(backend.embed_texts(["a red chair", "lamp"]), _unit(expected_texts), atol=1e-5)


def test_shapes_normalisation_batching_determinism(backend):
    rng = np.random.default_rng(4)
    crops = [rng.integers(0, 256, (int(h), int(w), 3), dtype=np.uint8) for h, w in rng.integers(5, 90, (21, 2))]
    batched = backend.embed_images(crops)  # 21 crops: two onnxruntime batches
    assert batched.shape == (21, 16) and batched.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(batched, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(batched, np.concatenate([backend.embed_images([c]) for c in crops]), atol=1e-5)
    np.testing.assert_array_equal(batched, backend.embed_images(crops))
    texts = [f"a {w} chair" for w in ("red", "photo", "lamp")] * 7
    embedded = backend.embed_texts(texts)
    assert embedded.shape == (21, 16)
    np.testing.assert_allclose(np.linalg.norm(embedded, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(embedded[:3], embedded[18:], atol=1e-6)
    assert backend.embed_images([]).shape == (0, 16) and backend.embed_texts([]).shape == (0, 16)
    with pytest.raises(ValueError):
        backend.embed_images([np.zeros((8, 8), np.uint8)])


def test_best_class_name_works_without_cached_class_embeddings(backend):
    from monovoc_ros.embed import conse_files as cf
    from monovoc_ros.embed.attributes import best_class_name, class_vocabulary, clean_class_name

    names, embeddings = class_vocabulary(backend)  # 1000 prompts through the tiny text encoder, cached
    assert len(names) == 1000 and embeddings.shape == (1000, 16)
    assert class_vocabulary(backend)[1] is embeddings
    noun = best_class_name(backend.embed_images([np.zeros((32, 32, 3), np.uint8)])[0], backend)
    assert noun in {clean_class_name(n) for n in cf.parse_class_names(cf.packaged_class_names_text())}


def test_missing_file_is_a_clear_error(exported, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(exported[1], broken)
    (broken / TEXTUAL_ONNX).unlink()
    with pytest.raises(ModelMissingError, match="lacks textual.onnx"):
        ClipOnnxBackend(broken)
    with pytest.raises(ModelMissingError):
        load_backend("clip_onnx", model_dir=tmp_path / "does-not-exist")


def test_mismatched_dims_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="mismatched embedding dims.*16.*8"):
        tokenizer = _tokenizer_json(tmp_path / "t.json")
        export_clip_onnx(TinyClip(image_dim=16, text_dim=8), tmp_path / "m", tokenizer, CONFIG)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"image_szie": 32}, "unknown"),
        ({"image_mean": [0.5, 0.4]}, "image_mean"),
        ({"image_std": [0.2, 0.0, 0.3]}, "positive"),
        ({"image_fit": "stretch"}, "image_fit"),
        ({"context_length": 9}, "context_length is 9"),
    ],
)
def test_bad_config_is_reported(exported, tmp_path, change, message):
    model_dir = tmp_path / "m"
    shutil.copytree(exported[1], model_dir)
    config = {**CONFIG, **change}
    if "image_szie" in change:
        del config["image_size"]
    (model_dir / CONFIG_JSON).write_text(json.dumps(config))
    with pytest.raises(ValueError, match=message):
        ClipOnnxBackend(model_dir)
