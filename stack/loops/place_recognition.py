"""Place recognition over camera key frames: a vocabulary tree of SIFT words with TF-IDF retrieval.

The method of the topological-map paper (section 2.1): a key frame (one image in ten) is blurred (Gaussian), its
Shi-Tomasi corners are found and described by SIFT descriptors (L2-normalised); the descriptors are
quantised by a vocabulary tree built by hierarchical k-means (Nister & Stewenius; ``cv2.kmeans``); each leaf is a
visual word with an inverted file (the key frames it occurs in); a query is scored against the
database with the TF-IDF model (Sivic & Zisserman) and the best-scoring earlier key frames are the
places it may be.

TF-IDF as computed here (``tests/unit/test_place_recognition.py`` checks a hand-computed case):

* ``tf(w, d) = n(w, d) / n(d)``: how often word w occurs in image d over the number of words in d;
* ``idf(w) = ln(N / N_w)``: N training images, N_w of them containing w. The weights come from the
  training images and are stored with the tree (Nister & Stewenius' choice), so a database that
  starts empty, as it does on a robot, scores its first key frames with stable weights. A word no
  training image contained gets ``ln(N / 1)`` (as rare as the rarest);
* a key frame's vector is ``v_d(w) = tf(w, d) * idf(w)``, L2-normalised, and the score of database
  image d for query q is the cosine ``<v_q, v_d>`` in [0, 1], summed over the inverted files of the
  query's words only.

Darkness: the colour camera is black (read noise only) in the dark. Corners are kept only where the
smaller eigenvalue of the blurred image's structure tensor exceeds an *absolute* threshold, and a key
frame with fewer than ``min_features`` such corners has no description (``describe`` returns None):
retrieval then proposes nothing, rather than matching noise to noise.

Files: ``VocabularyTree.save`` writes one ``.npz`` (no pickle), atomically; ``load`` validates it.
"""
from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from stack.errors import DopeSlamError

log = logging.getLogger(__name__)

FORMAT_VERSION = 1


class FeatureConfig(BaseModel):
    """Key-frame description: blur, Shi-Tomasi corners, SIFT descriptors."""

    model_config = ConfigDict(extra="forbid")

    blur_sigma_px: float = Field(1.2, ge=0.0, description="Gaussian blur before corner detection (0: none)")
    max_corners: int = Field(400, ge=1)
    quality_level: float = Field(0.01, gt=0.0, lt=1.0, description="Shi-Tomasi, relative to the strongest corner")
    min_distance_px: float = Field(5.0, ge=0.0, description="between corners, in the resized image")
    block_size: int = Field(3, ge=3, description="structure-tensor window (odd)")
    min_eigenvalue: float = Field(3e-5, ge=0.0, description="absolute floor on the smaller structure-tensor "
                                  "eigenvalue (image scaled to 0..1): rejects corners of sensor noise")
    min_features: int = Field(25, ge=1, description="fewer corners: the key frame has no description")
    descriptor_size_px: float = Field(10.0, gt=0.0, description="SIFT key-point diameter (resized image)")
    max_width_px: int = Field(320, ge=32, description="wider images are resized to this width first (SIFT builds "
                              "its pyramid from a doubled image: 640 px costs ~7x the time of 320 px)")


@dataclass
class KeyFrameFeatures:
    """Corners (N, 2) in pixels of the input image and their L2-normalised SIFT descriptors (N, 128)."""

    points_px: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.descriptors)


_sift = None


def _sift_extractor():
    global _sift
    if _sift is None:
        _sift = cv2.SIFT_create()
    return _sift


def describe(image: np.ndarray, config: FeatureConfig | None = None) -> KeyFrameFeatures | None:
    """Shi-Tomasi corners + SIFT descriptors of an RGB (H, W, 3) or grey (H, W) uint8 image.

    Returns None when fewer than ``min_features`` corners pass the absolute strength floor (a dark or
    featureless image): such a key frame must not be used for retrieval.
    """
    cfg = config or FeatureConfig()
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2 or img.size == 0:
        raise ValueError(f"describe: expected an (H, W) or (H, W, 3) image, got shape {np.shape(image)}")
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    scale = 1.0
    if img.shape[1] > cfg.max_width_px:
        scale = cfg.max_width_px / img.shape[1]
        img = cv2.resize(img, (cfg.max_width_px, int(round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    if cfg.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_sigma_px)
    corners = cv2.goodFeaturesToTrack(img, maxCorners=cfg.max_corners, qualityLevel=cfg.quality_level,
                                      minDistance=cfg.min_distance_px, blockSize=cfg.block_size)
    if corners is None:
        return None
    corners = corners.reshape(-1, 2)
    # goodFeaturesToTrack's threshold is relative to the image's strongest corner, so pure noise yields
    # corners too; keep only corners whose absolute strength says there is structure
    eig = cv2.cornerMinEigenVal(img.astype(np.float32) / 255.0, cfg.block_size)
    xi = np.clip(np.rint(corners[:, 0]).astype(int), 0, img.shape[1] - 1)
    yi = np.clip(np.rint(corners[:, 1]).astype(int), 0, img.shape[0] - 1)
    corners = corners[eig[yi, xi] >= cfg.min_eigenvalue]
    if len(corners) < cfg.min_features:
        return None
    kps = [cv2.KeyPoint(float(x), float(y), cfg.descriptor_size_px) for x, y in corners]
    kps, desc = _sift_extractor().compute(img, kps)
    if desc is None or len(kps) < cfg.min_features:
        return None
    desc = desc.astype(np.float32)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    pts = np.array([k.pt for k in kps], dtype=np.float32) / scale
    return KeyFrameFeatures(pts, desc)


# ---------------------------------------------------------------------------------------------
# hierarchical k-means


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """k-means with k-means++ seeding (OpenCV's ``cv2.kmeans``, its random stream seeded from ``rng``):
    (centres (k, D), labels (N,)). Requires len(x) >= k."""
    cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, iterations, 1e-6)
    _, labels, centres = cv2.kmeans(np.ascontiguousarray(x, dtype=np.float32), k, None, criteria, 1,
                                    cv2.KMEANS_PP_CENTERS)
    return centres.astype(np.float64), labels.ravel().astype(np.int64)


class VocabularyError(DopeSlamError, ValueError):
    """A vocabulary file that cannot be used; names the file and what is wrong."""


class VocabularyTree:
    """Hierarchical k-means tree. Node 0 is the root; ``children[i]`` lists up to ``branching`` child
    nodes (-1: none); a node without children is a leaf and carries a word id (``word_of_node``)."""

    def __init__(self, centres: np.ndarray, children: np.ndarray, word_of_node: np.ndarray, idf: np.ndarray,
                 branching: int, depth: int, training_images: int):
        self.centres = np.asarray(centres, dtype=np.float32)
        self.children = np.asarray(children, dtype=np.int32)
        self.word_of_node = np.asarray(word_of_node, dtype=np.int32)
        self.idf = np.asarray(idf, dtype=np.float64)
        self.branching = int(branching)
        self.depth = int(depth)
        self.training_images = int(training_images)
        self.feature_config = FeatureConfig()

    @property
    def n_words(self) -> int:
        return len(self.idf)

    # ------------------------------------------------------------------ building

    @classmethod
    def train(cls, descriptors_per_image: list[np.ndarray], branching: int = 8, depth: int = 4, seed: int = 0,
              iterations: int = 15, max_descriptors: int = 200_000) -> "VocabularyTree":
        """Hierarchical k-means over the training images' descriptors; IDF from the same images.

        ``branching`` children per node, ``depth`` levels: up to branching**depth words. A node with fewer
        than ``branching`` descriptors becomes a leaf early.
        """
        if branching < 2 or depth < 1:
            raise ValueError(f"vocabulary: expected branching >= 2 and depth >= 1, got {branching}, {depth}")
        descs = [np.asarray(d, dtype=np.float32).reshape(-1, 128) for d in descriptors_per_image if d is not None]
        if not descs or sum(len(d) for d in descs) < branching:
            raise ValueError("vocabulary: need at least `branching` descriptors to train")
        rng = np.random.default_rng(seed)
        x = np.concatenate(descs).astype(np.float64)
        if len(x) > max_descriptors:
            x = x[rng.choice(len(x), max_descriptors, replace=False)]
        centres = [np.zeros(128)]
        children = [[-1] * branching]
        members = {0: np.arange(len(x))}
        level_nodes = [0]
        for _ in range(depth):
            next_nodes = []
            for node in level_nodes:
                idx = members.pop(node)
                if len(idx) < branching:
                    continue
                c, lab = _kmeans(x[idx], branching, rng, iterations)
                for j in range(branching):
                    child = len(centres)
                    centres.append(c[j])
                    children.append([-1] * branching)
                    children[node][j] = child
                    members[child] = idx[lab == j]
                    next_nodes.append(child)
            level_nodes = next_nodes
        children = np.array(children, dtype=np.int32)
        is_leaf = (children < 0).all(1)
        word_of_node = np.full(len(children), -1, dtype=np.int32)
        word_of_node[is_leaf] = np.arange(int(is_leaf.sum()))
        tree = cls(np.array(centres), children, word_of_node, np.zeros(int(is_leaf.sum())), branching, depth, 0)
        tree.set_idf(descs)
        log.info("vocabulary tree: %d words (branching %d, depth %d) from %d descriptors of %d images",
                 tree.n_words, branching, depth, len(x), len(descs))
        return tree

    def set_idf(self, descriptors_per_image: list[np.ndarray]) -> None:
        """``idf(w) = ln(N / N_w)`` over these images; a word none of them contains gets ``ln(N)``."""
        n_images = len(descriptors_per_image)
        df = np.zeros(self.n_words)
        for d in descriptors_per_image:
            df[np.unique(self.quantize(d))] += 1
        self.idf = np.log(n_images / np.maximum(df, 1.0)) if n_images else np.zeros(self.n_words)
        self.training_images = n_images

    # ------------------------------------------------------------------ use

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id of each descriptor (N, 128): descend the tree to the nearest child at each level."""
        d = np.asarray(descriptors, dtype=np.float32).reshape(-1, 128)
        node = np.zeros(len(d), dtype=np.int64)
        for _ in range(self.depth):
            ch = self.children[node]  # (N, k)
            has = ch[:, 0] >= 0
            if not has.any():
                break
            c = self.centres[np.maximum(ch[has], 0)]  # (M, k, 128)
            dist = ((c - d[has, None, :]) ** 2).sum(-1)
            dist[ch[has] < 0] = np.inf
            node[has] = ch[has][np.arange(int(has.sum())), dist.argmin(1)]
        return self.word_of_node[node]

    def bow(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The normalised TF-IDF vector of one image, sparse: (word ids, weights with unit L2 norm)."""
        words = self.quantize(descriptors)
        if len(words) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        ids, counts = np.unique(words, return_counts=True)
        w = counts / len(words) * self.idf[ids]
        norm = np.linalg.norm(w)
        keep = w > 0
        return ids[keep].astype(np.int64), (w[keep] / norm if norm > 0 else w[keep])

    # ------------------------------------------------------------------ files

    def save(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez_compressed(f, format_version=np.int64(FORMAT_VERSION), centres=self.centres,
                                    children=self.children, word_of_node=self.word_of_node, idf=self.idf,
                                    branching=np.int64(self.branching), depth=np.int64(self.depth),
                                    training_images=np.int64(self.training_images),
                                    feature_config=np.array(self.feature_config.model_dump_json()))
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "VocabularyTree":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise VocabularyError(f"{path}: file not found") from None
        except (OSError, ValueError) as exc:
            raise VocabularyError(f"{path}: not a vocabulary .npz file ({exc})") from None
        need = ["format_version", "centres", "children", "word_of_node", "idf", "branching", "depth"]
        missing = [k for k in need if k not in data]
        if missing:
            raise VocabularyError(f"{path}: missing fields {missing}; expected a file written by VocabularyTree.save")
        if int(data["format_version"]) != FORMAT_VERSION:
            raise VocabularyError(f"{path}: field 'format_version': expected {FORMAT_VERSION}, "
                                  f"got {int(data['format_version'])}")
        n_nodes, k = data["children"].shape
        if data["centres"].shape != (n_nodes, 128) or data["word_of_node"].shape != (n_nodes,) \
                or k != int(data["branching"]) or int(data["word_of_node"].max()) + 1 != len(data["idf"]):
            raise VocabularyError(f"{path}: inconsistent shapes: centres {data['centres'].shape}, children "
                                  f"{data['children'].shape}, word_of_node {data['word_of_node'].shape}, "
                                  f"idf {data['idf'].shape}")
        tree = cls(data["centres"], data["children"], data["word_of_node"], data["idf"], int(data["branching"]),
                   int(data["depth"]), int(data.get("training_images", 0)))
        if "feature_config" in data:
            tree.feature_config = FeatureConfig.model_validate_json(str(data["feature_config"]))
        return tree


@dataclass
class Match:
    key_frame: int  # id in the database (insertion order)
    score: float  # TF-IDF cosine in [0, 1]


class PlaceDatabase:
    """Key frames as TF-IDF vectors with one inverted file per word; retrieval by cosine score."""

    def __init__(self, tree: VocabularyTree):
        self.tree = tree
        self._inv_docs: list[list[int]] = [[] for _ in range(tree.n_words)]
        self._inv_weights: list[list[float]] = [[] for _ in range(tree.n_words)]
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def add(self, descriptors: np.ndarray | None) -> int:
        """Add a key frame (its descriptors, or None for one without a description); returns its id."""
        doc = self._size
        self._size += 1
        if descriptors is not None and len(descriptors):
            ids, w = self.tree.bow(descriptors)
            for i, wi in zip(ids, w):
                self._inv_docs[i].append(doc)
                self._inv_weights[i].append(float(wi))
        return doc

    def scores(self, descriptors: np.ndarray) -> np.ndarray:
        """Cosine TF-IDF score of every key frame in the database for a query (0 for those sharing no word)."""
        out = np.zeros(self._size)
        ids, w = self.tree.bow(descriptors)
        for i, wi in zip(ids, w):
            docs = self._inv_docs[i]
            if docs:
                np.add.at(out, np.asarray(docs), wi * np.asarray(self._inv_weights[i]))
        return out

    def query(self, descriptors: np.ndarray | None, k: int = 5, before: int | None = None,
              min_score: float = 0.0) -> list[Match]:
        """The ``k`` best key frames with id < ``before`` (all when None) scoring at least ``min_score``."""
        if descriptors is None or len(descriptors) == 0 or self._size == 0:
            return []
        s = self.scores(descriptors)
        if before is not None:
            s = s[:max(0, before)]
        order = np.argsort(-s, kind="stable")[:k]
        return [Match(int(i), float(s[i])) for i in order if s[i] >= min_score and s[i] > 0]
