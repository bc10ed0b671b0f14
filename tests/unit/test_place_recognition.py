"""Place recognition: key-frame description (and its refusal in the dark), the vocabulary tree, TF-IDF."""
import math

import cv2
import numpy as np
import pytest

from stack.loops.place_recognition import (FeatureConfig, PlaceDatabase, VocabularyError, VocabularyTree, describe)

E = np.eye(128, dtype=np.float32)


def hand_tree() -> VocabularyTree:
    """Branching 2, depth 2: words 0..3 are the unit descriptors e0..e3; e_k quantises to word k."""
    centres = np.zeros((7, 128), dtype=np.float32)
    centres[1], centres[2] = (E[0] + E[1]) / 2, (E[2] + E[3]) / 2
    centres[3:7] = E[0:4]
    children = np.array([[1, 2], [3, 4], [5, 6], [-1, -1], [-1, -1], [-1, -1], [-1, -1]])
    word_of_node = np.array([-1, -1, -1, 0, 1, 2, 3])
    return VocabularyTree(centres, children, word_of_node, np.zeros(4), branching=2, depth=2, training_images=0)


def image_of(words):
    return E[list(words)]


def test_tfidf_scores_match_a_hand_computed_case():
    tree = hand_tree()
    np.testing.assert_array_equal(tree.quantize(E[[3, 0, 2, 1]]), [3, 0, 2, 1])
    # training images {w0,w1} {w0,w2} {w0,w3} {w1}: N = 4, N_w = 3, 2, 1, 1
    tree.set_idf([image_of([0, 1]), image_of([0, 2]), image_of([0, 3]), image_of([1])])
    idf = [math.log(4 / 3), math.log(2), math.log(4), math.log(4)]
    np.testing.assert_allclose(tree.idf, idf)

    db = PlaceDatabase(tree)
    db.add(image_of([0, 0, 1]))  # A: tf(w0) = 2/3, tf(w1) = 1/3
    db.add(image_of([2, 3]))  # B: tf(w2) = tf(w3) = 1/2
    db.add(image_of([1, 2, 2, 3]))  # C: 1/4, 2/4, 1/4 of w1, w2, w3
    db.add(None)  # a key frame without description (dark): in the database, never matched
    q = image_of([0, 1, 2])  # tf 1/3 each

    # by hand: v = tf * idf, cosine of the two vectors
    a = np.array([2 / 3 * idf[0], 1 / 3 * idf[1], 0, 0])
    b = np.array([0, 0, 1 / 2 * idf[2], 1 / 2 * idf[3]])
    c = np.array([0, 1 / 4 * idf[1], 2 / 4 * idf[2], 1 / 4 * idf[3]])
    v = np.array([1 / 3 * idf[0], 1 / 3 * idf[1], 1 / 3 * idf[2], 0])
    cos = [x @ v / np.linalg.norm(x) / np.linalg.norm(v) for x in (a, b, c)]
    np.testing.assert_allclose(cos, [0.45489, 0.62183, 0.86356], atol=5e-6)  # the numbers, worked out on paper
    np.testing.assert_allclose(db.scores(q), cos + [0.0], atol=1e-9)

    best = db.query(q, k=2)
    assert [m.key_frame for m in best] == [2, 1]
    assert [m.key_frame for m in db.query(q, k=5, before=2)] == [1, 0]  # only key frames 0, 1 are old enough
    assert [m.key_frame for m in db.query(q, k=5, min_score=0.6)] == [2, 1]
    assert db.query(None) == []


def textured_image(seed: int, w=640, h=480) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((h, w, 3), 120, np.uint8)
    for _ in range(60):
        x, y = rng.integers(0, w - 40), rng.integers(0, h - 40)
        cv2.rectangle(img, (int(x), int(y)), (int(x + rng.integers(10, 60)), int(y + rng.integers(10, 60))),
                      tuple(int(v) for v in rng.integers(0, 255, 3)), -1)
    return img


def sensor_noise(img, light, seed):
    """The colour sensor at light level ``light``: exposure scaled, read noise 2 DN, shot noise (sim.camera)."""
    rng = np.random.default_rng(seed)
    x = img.astype(np.float32) * light
    x += rng.standard_normal(x.shape) * 2.0 + rng.standard_normal(x.shape) * np.sqrt(np.maximum(x, 0) / 50)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def test_dark_images_get_no_description_lit_ones_do():
    img = textured_image(0)
    lit = describe(sensor_noise(img, 1.0, 1))
    assert lit is not None and len(lit) >= 100
    assert lit.descriptors.shape == (len(lit), 128)
    np.testing.assert_allclose(np.linalg.norm(lit.descriptors, axis=1), 1.0, atol=1e-5)
    assert describe(sensor_noise(img, 0.0, 2)) is None  # black: read noise only
    assert describe(np.zeros((480, 640), np.uint8)) is None
    assert describe(np.full((480, 640, 3), 128, np.uint8)) is None  # featureless wall
    with pytest.raises(ValueError, match="expected an"):
        describe(np.zeros((4, 4, 4, 4), np.uint8))


def test_retrieval_finds_the_same_place_among_others(tmp_path):
    places = [textured_image(s) for s in range(8)]
    feats = [describe(sensor_noise(p, 1.0, 10 + i)) for i, p in enumerate(places)]
    tree = VocabularyTree.train([f.descriptors for f in feats], branching=6, depth=3, seed=0)
    assert tree.n_words > 36
    db = PlaceDatabase(tree)
    for f in feats:
        db.add(f.descriptors)
    for i, p in enumerate(places):
        # the same place seen again: shifted by 12 px, a little darker, other noise
        again = np.roll(sensor_noise(p, 0.85, 100 + i), 12, axis=1)
        best = db.query(describe(again).descriptors, k=2)
        assert best[0].key_frame == i
        assert best[0].score > 2 * best[1].score

    # save / load round trip: same words, same scores
    path = tree.save(tmp_path / "voc.npz")
    tree2 = VocabularyTree.load(path)
    d = feats[3].descriptors
    np.testing.assert_array_equal(tree.quantize(d), tree2.quantize(d))
    np.testing.assert_allclose(tree.idf, tree2.idf)
    assert tree2.branching == 6 and tree2.depth == 3 and tree2.feature_config == FeatureConfig()


def test_training_is_deterministic_and_respects_branching_and_depth():
    rng = np.random.default_rng(0)
    d = rng.standard_normal((3000, 128)).astype(np.float32)
    t1 = VocabularyTree.train([d[:1500], d[1500:]], branching=4, depth=3, seed=7)
    t2 = VocabularyTree.train([d[:1500], d[1500:]], branching=4, depth=3, seed=7)
    assert t1.n_words == 4 ** 3
    np.testing.assert_array_equal(t1.centres, t2.centres)
    assert (t1.children >= 0).sum(1).max() == 4
    with pytest.raises(ValueError, match="branching"):
        VocabularyTree.train([d], branching=1, depth=2)


def test_bad_vocabulary_files_are_named(tmp_path):
    with pytest.raises(VocabularyError, match="not found"):
        VocabularyTree.load(tmp_path / "none.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(VocabularyError, match="bad.npz"):
        VocabularyTree.load(bad)
    np.savez(tmp_path / "partial.npz", centres=np.zeros((1, 128)))
    with pytest.raises(VocabularyError, match="missing fields"):
        VocabularyTree.load(tmp_path / "partial.npz")
