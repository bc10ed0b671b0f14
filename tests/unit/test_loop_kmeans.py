"""The vocabulary tree's k-means (``cv2.kmeans``) against the hand-written Lloyd's k-means it replaced
(kept here as the reference): the same clusters on separated data, the same quality (within-cluster
sum of squares within 3 %) and the same retrieval on SIFT descriptors of real images."""
import cv2
import numpy as np

from stack.loops.place_recognition import PlaceDatabase, VocabularyTree, _kmeans, describe


def lloyd_reference(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int):
    """Lloyd's k-means with k-means++ seeding, as the vocabulary tree had it before ``cv2.kmeans``."""
    n = len(x)
    centres = np.empty((k, x.shape[1]), dtype=np.float64)
    centres[0] = x[rng.integers(n)]
    d2 = ((x - centres[0]) ** 2).sum(1)
    for j in range(1, k):
        total = d2.sum()
        i = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
        centres[j] = x[i]
        d2 = np.minimum(d2, ((x - centres[j]) ** 2).sum(1))
    x2 = (x ** 2).sum(1)
    labels = np.zeros(n, dtype=np.int64)
    for it in range(iterations):
        dist = x2[:, None] - 2.0 * x @ centres.T + (centres ** 2).sum(1)[None, :]
        new = dist.argmin(1)
        if it > 0 and np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            members = x[labels == j]
            if len(members):
                centres[j] = members.mean(0)
            else:
                far = int(dist[np.arange(n), labels].argmax())
                centres[j] = x[far]
    return centres, labels


def sse(x, centres, labels) -> float:
    return float(((x - centres[labels]) ** 2).sum())


def test_same_clusters_as_the_reference_on_separated_blobs():
    rng = np.random.default_rng(0)
    true_centres = rng.uniform(0, 100, (6, 16))
    x = np.concatenate([c + rng.normal(0, 1.0, (80, 16)) for c in true_centres])
    c_ref, l_ref = lloyd_reference(x, 6, np.random.default_rng(1), 15)
    c_new, l_new = _kmeans(x, 6, np.random.default_rng(1), 15)
    # the same partition up to the clusters' order, centres within 1e-4 (float32 arithmetic)
    perm = {int(a): int(b) for a, b in zip(l_ref, l_new)}
    assert len(set(perm.values())) == 6
    np.testing.assert_array_equal([perm[int(a)] for a in l_ref], l_new)
    for a, b in perm.items():
        np.testing.assert_allclose(c_new[b], c_ref[a], atol=1e-4)


def _textured(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((240, 320, 3), 128, np.uint8)
    for _ in range(60):
        x, y = (int(v) for v in rng.integers(0, [300, 220]))
        w, h = (int(v) for v in rng.integers(8, 40, 2))
        cv2.rectangle(img, (x, y), (x + w, y + h), tuple(int(c) for c in rng.integers(0, 255, 3)), -1)
    return img


def test_sift_vocabulary_quality_and_retrieval_match_the_reference():
    descs = [describe(_textured(s)).descriptors for s in range(12)]
    x = np.concatenate(descs).astype(np.float64)
    ref = [sse(x, *lloyd_reference(x, 10, np.random.default_rng(s), 15)) for s in range(3)]
    new = [sse(x, *_kmeans(x, 10, np.random.default_rng(s), 15)) for s in range(3)]
    assert abs(np.mean(new) / np.mean(ref) - 1.0) < 0.03, (ref, new)
    # a tree from these images retrieves each image as itself
    tree = VocabularyTree.train(descs, branching=4, depth=3, seed=0)
    db = PlaceDatabase(tree)
    for d in descs:
        db.add(d)
    assert [int(np.argmax(db.scores(d))) for d in descs] == list(range(len(descs)))


def test_seeded():
    x = np.random.default_rng(3).normal(size=(300, 8))
    a = _kmeans(x, 5, np.random.default_rng(7), 15)
    b = _kmeans(x, 5, np.random.default_rng(7), 15)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[0], b[0])
