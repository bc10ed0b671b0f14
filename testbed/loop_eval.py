"""The place-recognition evaluation of the topological-map paper (section 4.1, Figure 11), on a route driven twice.

Protocol (as in the paper's Lab experiment): the robot drives the same closed loop twice; the key frames
(one image in ten) of the first lap form the database, and each key frame of the second lap is a query
that should retrieve the database image of the same place. By default the vocabulary tree is built from
the first lap's key frames, as the seed did; ``vocabulary=`` may name a tree trained elsewhere.

Ground truth: a retrieved key frame is the same place when the two camera positions are within
``same_place_m`` and their headings within ``same_heading_deg`` (from the simulator). A query counts
for recall when some database key frame is the same place.

Baseline: SeqSLAM (Milford & Wyeth 2012), the method the seed compares with: images reduced to 64 x 48
grey and patch-normalised, a difference matrix, local contrast enhancement, and the best straight
sequence of ``ds`` frames through it at speeds ``v_min..v_max``; its confidence is the ratio of the best
sequence score outside a window around the match to the best.

Both methods give one match per query with a confidence; sweeping a threshold on the confidence gives
the precision-recall curve. The seed reports no figure for the recall at which it calls retrieval
usable (Figure 11 shows matched frames as dots), so the report gives the whole curve, the recall
reached at 95 % and at 100 % precision, and the precision at the recall levels in ``RECALL_LEVELS``.

Output: ``loop_eval.json`` and ``loop_eval.png`` (Figure 11 style: matched database index over query
index, red the vocabulary tree, blue SeqSLAM, grey the truth; and the precision-recall curves).
"""
from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from stack.loops.place_recognition import FeatureConfig, PlaceDatabase, VocabularyTree, describe

log = logging.getLogger(__name__)

RECALL_LEVELS = (0.25, 0.5, 0.75)
DEFAULT_SCENARIO = "office_loop_twice"


# ---------------------------------------------------------------------------------------------
# SeqSLAM


def seqslam_preprocess(image: np.ndarray, size=(64, 48), patch: int = 8) -> np.ndarray:
    """Grey, downsampled, patch-normalised (each patch zero mean, unit deviation) image as float32."""
    g = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    g = cv2.resize(g, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    h, w = g.shape
    out = np.zeros_like(g)
    for y in range(0, h, patch):
        for x in range(0, w, patch):
            p = g[y:y + patch, x:x + patch]
            sd = p.std()
            out[y:y + patch, x:x + patch] = (p - p.mean()) / sd if sd > 1e-6 else 0.0
    return out


def seqslam(db_images: list[np.ndarray], query_images: list[np.ndarray], ds: int = 10, window: int = 10,
            v_min: float = 0.8, v_max: float = 1.25, v_steps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Per query: (best database index (-1: none yet), confidence = second best / best sequence score)."""
    A = np.stack([seqslam_preprocess(im).ravel() for im in db_images])
    B = np.stack([seqslam_preprocess(im).ravel() for im in query_images])
    D = np.abs(B[:, None, :] - A[None, :, :]).mean(-1)  # (Nq, Nd)
    # local contrast enhancement along the database, per query
    Dn = np.empty_like(D)
    nd = D.shape[1]
    for j in range(nd):
        lo, hi = max(0, j - window // 2), min(nd, j + window // 2 + 1)
        mu, sd = D[:, lo:hi].mean(1), D[:, lo:hi].std(1)
        Dn[:, j] = (D[:, j] - mu) / np.maximum(sd, 1e-6)
    best = np.full(len(B), -1)
    conf = np.zeros(len(B))
    speeds = np.linspace(v_min, v_max, v_steps)
    for i in range(ds - 1, len(B)):
        score = np.full(nd, np.inf)
        for v in speeds:
            s = np.zeros(nd)
            for k in range(ds):  # query i - k sits k * v database frames before j
                off = int(round(v * k))
                row = np.full(nd, np.inf)
                row[off:] = Dn[i - k, :nd - off] if off < nd else np.inf
                s += row
            score = np.minimum(score, s)
        j = int(np.argmin(score))
        if not np.isfinite(score[j]):
            continue
        outside = np.ones(nd, bool)
        outside[max(0, j - window):j + window + 1] = False
        # the scores are sums of z-scores (negative is good): shift so the worst sequence scores zero
        finite = np.isfinite(score)
        ref = score[finite].max()
        b = ref - score[j]
        second = ref - score[outside & finite].min() if (outside & finite).any() else 0.0
        best[i] = j
        conf[i] = b / max(second, 1e-9)
    return best, conf


# ---------------------------------------------------------------------------------------------
# evaluation


def heading_of_camera(T_world_camera: np.ndarray) -> np.ndarray:
    """Heading (rad) of the optical axis (z) in the world's xy plane."""
    z = T_world_camera[..., :3, 2]
    return np.arctan2(z[..., 1], z[..., 0])


def split_laps(positions: np.ndarray, away_m: float = 10.0, back_m: float = 1.5) -> int:
    """Index of the first key frame after the robot, having gone ``away_m`` from its start, is back
    within ``back_m`` of it: the start of the second lap."""
    d = np.linalg.norm(positions[:, :2] - positions[0, :2], axis=1)
    far = np.flatnonzero(d > away_m)
    if not len(far):
        raise ValueError(f"the route never goes {away_m} m from its start: not a loop driven twice")
    back = np.flatnonzero((np.arange(len(d)) > far[0]) & (d < back_m))
    if not len(back):
        raise ValueError("the route does not come back to its start: not a loop driven twice")
    return int(back[0])


def same_place(pos_a, head_a, pos_b, head_b, dist_m: float, heading_deg: float) -> np.ndarray:
    """(Nb, Na) truth matrix."""
    d = np.linalg.norm(pos_b[:, None, :2] - pos_a[None, :, :2], axis=-1)
    dh = np.abs((head_b[:, None] - head_a[None, :] + np.pi) % (2 * np.pi) - np.pi)
    return (d <= dist_m) & (dh <= np.radians(heading_deg))


def pr_curve(confidence: np.ndarray, correct: np.ndarray, positives: int) -> dict:
    """Precision and recall as the confidence threshold sweeps down through the matches."""
    valid = np.isfinite(confidence) & (confidence > 0)
    order = np.argsort(-confidence[valid], kind="stable")
    c = correct[valid][order]
    tp = np.cumsum(c)
    n = np.arange(1, len(c) + 1)
    precision = tp / n
    recall = tp / max(positives, 1)
    thresholds = confidence[valid][order]

    def best_recall_at(p_min):
        ok = precision >= p_min
        return float(recall[ok].max()) if ok.any() else 0.0

    def precision_at(r):
        ok = recall >= r
        return float(precision[ok].max()) if ok.any() else None

    ap = float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision)) if len(c) else 0.0
    return {"precision": precision.tolist(), "recall": recall.tolist(), "thresholds": thresholds.tolist(),
            "recall_at_precision_95": best_recall_at(0.95), "recall_at_precision_100": best_recall_at(1.0),
            "precision_at_recall": {f"{r:.2f}": precision_at(r) for r in RECALL_LEVELS},
            "average_precision": ap, "threshold_at_precision_95": _threshold_at(precision, thresholds, 0.95)}


def _threshold_at(precision, thresholds, p_min):
    """The lowest confidence threshold whose matches above it still have precision >= p_min."""
    ok = np.flatnonzero(precision >= p_min)
    return float(thresholds[ok[-1]]) if len(ok) else None


def evaluate(images, stamps, T_world_camera, vocabulary: VocabularyTree | None = None, branching: int = 10,
             depth: int = 3, same_place_m: float = 2.0, same_heading_deg: float = 45.0,
             features: FeatureConfig | None = None, seed: int = 0) -> dict:
    """The evaluation on one route driven twice (key frames, their stamps and camera poses)."""
    features = features or (vocabulary.feature_config if vocabulary is not None else FeatureConfig())
    pos = T_world_camera[:, :3, 3]
    head = heading_of_camera(T_world_camera)
    split = split_laps(pos)
    ia, ib = np.arange(split), np.arange(split, len(images))
    t0 = time.perf_counter()
    feats = [describe(im, features) for im in images]
    t_describe = (time.perf_counter() - t0) / len(images)
    vocab_source = "given"
    if vocabulary is None:
        vocabulary = VocabularyTree.train([feats[i].descriptors for i in ia if feats[i] is not None],
                                          branching=branching, depth=depth, seed=seed)
        vocab_source = "first lap (seed protocol)"
    db = PlaceDatabase(vocabulary)
    for i in ia:
        db.add(feats[i].descriptors if feats[i] is not None else None)
    truth = same_place(pos[ia], head[ia], pos[ib], head[ib], same_place_m, same_heading_deg)
    positives = int(truth.any(1).sum())

    vt_match = np.full(len(ib), -1)
    vt_conf = np.zeros(len(ib))
    t0 = time.perf_counter()
    for q, i in enumerate(ib):
        if feats[i] is None:
            continue
        m = db.query(feats[i].descriptors, k=1)
        if m:
            vt_match[q], vt_conf[q] = m[0].key_frame, m[0].score
    t_query = (time.perf_counter() - t0) / len(ib)
    t0 = time.perf_counter()
    sq_match, sq_conf = seqslam([images[i] for i in ia], [images[i] for i in ib])
    t_seq = (time.perf_counter() - t0) / len(ib)

    def correct_of(match):
        return np.array([m >= 0 and bool(truth[q, m]) for q, m in enumerate(match)])

    vt_ok, sq_ok = correct_of(vt_match), correct_of(sq_match)
    nearest = np.linalg.norm(pos[ib][:, None, :2] - pos[ia][None, :, :2], axis=-1).argmin(1)
    return {
        "database_key_frames": int(len(ia)), "query_key_frames": int(len(ib)), "queries_with_a_true_match": positives,
        "same_place_m": same_place_m, "same_heading_deg": same_heading_deg,
        "described_key_frames": int(sum(f is not None for f in feats)),
        "vocabulary": {"source": vocab_source, "words": vocabulary.n_words, "branching": vocabulary.branching,
                       "depth": vocabulary.depth},
        "vocabulary_tree": {**pr_curve(vt_conf, vt_ok, positives), "match": vt_match.tolist(),
                            "confidence": vt_conf.tolist(), "correct": vt_ok.tolist(),
                            "seconds_per_key_frame_describe": t_describe, "seconds_per_query": t_query},
        "seqslam": {**pr_curve(sq_conf, sq_ok, positives), "match": sq_match.tolist(), "confidence": sq_conf.tolist(),
                    "correct": sq_ok.tolist(), "seconds_per_query": t_seq},
        "truth_nearest": nearest.tolist(), "truth_any": truth.any(1).tolist(),
        "stamps_database": stamps[ia].tolist(), "stamps_query": stamps[ib].tolist(),
    }


def figure(result: dict, path: Path, title: str) -> None:
    from testbed.plots import plt, save

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5))
    q = np.arange(result["query_key_frames"])
    has = np.array(result["truth_any"])
    ax.plot(q[has], np.array(result["truth_nearest"])[has], "-", color="0.75", lw=4, label="same place (truth)")
    for key, color, name in (("seqslam", "tab:blue", "SeqSLAM"), ("vocabulary_tree", "red", "vocabulary tree")):
        r = result[key]
        thr = r["threshold_at_precision_95"]
        m, c = np.array(r["match"]), np.array(r["confidence"])
        shown = (m >= 0) & (c >= (thr if thr is not None else np.inf))
        ax.plot(q[shown], m[shown], "o", color=color, ms=3.5 if key == "seqslam" else 2.5,
                label=f"{name} ({int(shown.sum())} matches at precision >= 95%)")
        bx.plot(r["recall"], r["precision"], "-", color=color, label=f"{name} (AP {r['average_precision']:.2f})")
    ax.set_xlabel("query key frame (second lap)")
    ax.set_ylabel("matched key frame (first lap)")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(title, fontsize=9)
    bx.axhline(0.95, color="0.5", ls=":", lw=1)
    bx.set_xlim(0, 1.02)
    bx.set_ylim(0, 1.02)
    bx.set_xlabel("recall")
    bx.set_ylabel("precision")
    bx.legend(fontsize=8, loc="lower left")
    bx.set_title("same-place retrieval, precision-recall", fontsize=9)
    save(fig, path)


def run_loop_eval(scenario: str = DEFAULT_SCENARIO, out_dir: str = "out/loop_eval", seed: int | None = None,
                  duration: float | None = None, vocabulary: str | None = None, branching: int = 10,
                  depth: int = 3, keep_key_frames: bool = False) -> dict:
    """``keep_key_frames``: save the rendered key frames to OUT/key_frames.npz, and reuse that file
    (if it is there) instead of simulating again."""
    from testbed.io import write_json
    from testbed.vocabulary import key_frame_images

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "key_frames.npz"
    t0 = time.perf_counter()
    if keep_key_frames and cache.exists():
        with np.load(cache, allow_pickle=False) as z:
            if str(z["scenario"]) != scenario:
                raise ValueError(f"{cache}: key frames of scenario {str(z['scenario'])!r}, not {scenario!r}")
            images, stamps, T_wc = list(z["images"]), z["stamps"], z["T_world_camera"]
        log.info("key frames from %s", cache)
    else:
        images, stamps, T_wc = key_frame_images(scenario, seed=seed, duration=duration)
        if keep_key_frames:
            tmp = out / "key_frames.tmp.npz"
            np.savez_compressed(tmp, images=np.array(images), stamps=stamps, T_world_camera=T_wc,
                                scenario=np.array(scenario))
            tmp.replace(cache)
    t_sim = time.perf_counter() - t0
    tree = VocabularyTree.load(vocabulary) if vocabulary else None
    result = evaluate(images, stamps, T_wc, tree, branching, depth)
    result.update({"scenario": scenario, "seed": seed, "simulation_seconds": t_sim})
    write_json(out / "loop_eval.json", result)
    figure(result, out / "loop_eval.png", f"{scenario}: key frames of lap 2 retrieved among lap 1")
    return result


def print_summary(r: dict) -> None:
    print(f"{r['scenario']}: {r['database_key_frames']} database key frames (lap 1), {r['query_key_frames']} queries "
          f"(lap 2), {r['queries_with_a_true_match']} with a true match; vocabulary {r['vocabulary']['words']} words "
          f"({r['vocabulary']['source']})")
    print(f"{'method':<16} {'AP':>5} {'R@P95':>6} {'R@P100':>7} " + " ".join(f"P@R{k:>5}" for k in
                                                                         r["vocabulary_tree"]["precision_at_recall"]))
    for key, name in (("vocabulary_tree", "vocabulary tree"), ("seqslam", "SeqSLAM")):
        x = r[key]
        pr = " ".join(f"{'-' if v is None else f'{100 * v:.0f}%':>9}" for v in x["precision_at_recall"].values())
        print(f"{name:<16} {x['average_precision']:5.2f} {100 * x['recall_at_precision_95']:5.0f}% "
              f"{100 * x['recall_at_precision_100']:6.0f}% {pr}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``dopeslam loop-eval``."""
    p.add_argument("scenario", nargs="?", default=DEFAULT_SCENARIO)
    p.add_argument("--out", default="out/loop_eval")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--vocabulary", default=None, help="a vocabulary .npz (default: trained on the first lap)")
    p.add_argument("--branching", type=int, default=10)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--keep-key-frames", action="store_true", help="save (and reuse) OUT/key_frames.npz")


def run_args(a) -> int:
    r = run_loop_eval(a.scenario, a.out, a.seed, a.duration, a.vocabulary, a.branching, a.depth, a.keep_key_frames)
    print_summary(r)
    print(f"wrote {a.out}/loop_eval.json, loop_eval.png")
    return 0
