"""Train and evaluate the topological-map paper's colour-verified HOG detector (``stack.topomap.hog_detector``).

Training data: the DOPE data shards (``sim.datagen``: our renderer, domain-randomised rooms, the six
objects), shards with index % 5 != 4; held out for testing: index % 5 == 4. Boxes are the tight
visible boxes from the shards' segmentation.

Evaluation (the paper's Figure 20 / Table 4): PASCAL VOC protocol per class: a detection is correct
when its IoU with an unclaimed true box of its class is >= 0.5; true boxes that are small (< 16 px
tall at 320 x 240) or mostly hidden (< 50 % visible) are "difficult" (neither missed nor false when
detected); AP is the area under the interpolated precision-recall curve (all points). With the
colour step, detections whose colour-name histogram fails the class's colour model are removed
before ranking. Test images: the held-out shards and, separately, frames of the bundled lit
scenarios' camera streams (every 5th frame).

    dopeslam hog-detector train [--data runs/data/rgbd_v1] [--max-images N]
    dopeslam hog-detector eval --out out/topomap/detector
    dopeslam hog-detector table out/topomap/detector/detector.json
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from stack.topomap.hog_detector import (DEFAULT_COLOUR, DEFAULT_WEIGHTS, HogDetector, TrainingImage, fit_colour_model, iou,
                                load_shard_images, train_detector)
from testbed.topomap import InputError, print_saved_report

log = logging.getLogger(__name__)
CLASSES = ("OrangeJuice", "Yogurt", "Mustard", "Raisins", "Cookies", "E")
DEFAULT_DATA = Path("runs/data/rgbd_v1")
MIN_BOX_H = 16.0
MIN_VISIBLE = 0.5
IOU = 0.5


def shard_split(data_dir: Path) -> tuple[list[int], list[int]]:
    idx = sorted(int(p.stem.split("_")[1]) for p in data_dir.glob("shard_*.json") if p.with_suffix(".npz").exists())
    return [i for i in idx if i % 5 != 4], [i for i in idx if i % 5 == 4]


def train(data_dir: Path = DEFAULT_DATA, out: Path = DEFAULT_WEIGHTS, colour_out: Path = DEFAULT_COLOUR,
          max_images: int | None = None, seed: int = 0, mining_rounds: int = 1, mining_images: int = 200) -> dict:
    train_shards, test_shards = shard_split(data_dir)
    if not train_shards:
        raise InputError(f"{data_dir}: no data shards (shard_NNNNN.npz + .json); generate them with `dopeslam datagen`")
    t0 = time.perf_counter()
    images = load_shard_images(data_dir, train_shards, CLASSES)
    if max_images:
        images = images[:max_images]
    log.info("training on %d images of %d shards", len(images), len(train_shards))
    det = train_detector(images, list(CLASSES), seed=seed, mining_rounds=mining_rounds, mining_images=mining_images)
    det.colour = fit_colour_model(images, list(CLASSES))
    det.save(out, colour_out)
    info = {"train_shards": train_shards, "test_shards": test_shards, "images": len(images),
            "components": [{"class": c.cls, "shape": list(c.shape)} for c in det.components],
            "seconds": time.perf_counter() - t0, "colour_thresholds": det.colour.thresholds}
    from testbed.io import write_json

    write_json(Path(out).with_suffix(".json"), info, indent=1)
    log.info("saved %s and %s (%.0f s)", out, colour_out, info["seconds"])
    return info


# --- evaluation ------------------------------------------------------------------------------------

def average_precision(recall: np.ndarray, precision: np.ndarray) -> float:
    """VOC all-points AP: area under the precision envelope."""
    r = np.r_[0.0, recall, 1.0]
    p = np.r_[0.0, precision, 0.0]
    for i in range(len(p) - 2, -1, -1):
        p[i] = max(p[i], p[i + 1])
    k = np.flatnonzero(r[1:] != r[:-1])
    return float(np.sum((r[k + 1] - r[k]) * p[k + 1]))


def pr_curve(dets: list[tuple[int, float, np.ndarray]], truths: dict[int, tuple[np.ndarray, np.ndarray]]) -> dict:
    """dets: (image, score, box) of one class; truths: image -> (boxes (M, 4), difficult (M,))."""
    n_pos = int(sum((~d).sum() for _, d in truths.values()))
    order = sorted(range(len(dets)), key=lambda i: -dets[i][1])
    claimed = {k: np.zeros(len(v[0]), bool) for k, v in truths.items()}
    tp, fp, scores = [], [], []
    for i in order:
        im, score, box = dets[i]
        boxes, difficult = truths.get(im, (np.zeros((0, 4)), np.zeros(0, bool)))
        if len(boxes):
            o = iou(box[None], boxes)[0]
            j = int(np.argmax(o))
            if o[j] >= IOU:
                if difficult[j]:
                    continue  # neither right nor wrong
                if not claimed[im][j]:
                    claimed[im][j] = True
                    tp.append(1)
                    fp.append(0)
                    scores.append(score)
                    continue
        tp.append(0)
        fp.append(1)
        scores.append(score)
    tp = np.cumsum(tp)
    fp = np.cumsum(fp)
    recall = tp / max(n_pos, 1)
    precision = tp / np.maximum(tp + fp, 1)
    return {"recall": recall, "precision": precision, "scores": np.array(scores), "positives": n_pos,
            "ap": average_precision(recall, precision) if len(recall) else 0.0}


def precision_at(curve: dict, recall: float) -> float | None:
    """Best precision at recall >= ``recall`` (None if the curve never gets there)."""
    r, p = curve["recall"], curve["precision"]
    ok = r >= recall - 1e-12
    return float(p[ok].max()) if ok.any() else None


def test_images_from_streams(scenarios=("experiment3_columns", "shelf_corridor"), every: int = 5) -> list[TrainingImage]:
    from testbed.topomap.stream import camera_stream

    out = []
    for name in scenarios:
        s = camera_stream(name)
        f = 320 / s.info.width
        for i in range(0, len(s), every):
            ok = np.isfinite(s.boxes[i, :, 0])
            rgb = cv2.resize(s.rgb[i], (320, int(round(s.info.height * f))), interpolation=cv2.INTER_AREA)
            out.append(TrainingImage(rgb, s.boxes[i][ok] * f, [o.cls for o, k in zip(s.objects, ok) if k],
                                     s.visible[i][ok]))
    return out


def evaluate(det: HogDetector, images: list[TrainingImage], label: str) -> dict:
    truths = {c: {} for c in CLASSES}
    for k, im in enumerate(images):
        for c in CLASSES:
            sel = [j for j, cc in enumerate(im.classes) if cc == c]
            b = im.boxes[sel].reshape(-1, 4)
            difficult = ((b[:, 3] - b[:, 1]) < MIN_BOX_H) | (im.visible[sel] < MIN_VISIBLE)
            truths[c][k] = (b, difficult)
    dets_all = {c: [] for c in CLASSES}
    dets_col = {c: [] for c in CLASSES}
    t0 = time.perf_counter()
    last = t0
    for k, im in enumerate(images):
        for d in det.detect(im.rgb, threshold=-1.0, colour_step=False):
            dets_all[d.cls].append((k, d.score, d.box))
            if d.colour_pass is not False:
                dets_col[d.cls].append((k, d.score, d.box))
        if time.perf_counter() - last > 20:
            last = time.perf_counter()
            log.info("%s: %d / %d images", label, k + 1, len(images))
    secs = (time.perf_counter() - t0) / max(1, len(images))
    res = {"images": len(images), "seconds_per_image": secs, "classes": {}}
    for c in CLASSES:
        a = pr_curve(dets_all[c], truths[c])
        b = pr_curve(dets_col[c], truths[c])
        rmax = float(b["recall"].max()) if len(b["recall"]) else 0.0
        levels = [0.1, 0.25, 0.5]
        res["classes"][c] = {
            "positives": a["positives"], "ap_shape": a["ap"], "ap_colour": b["ap"],
            "max_recall_shape": float(a["recall"].max()) if len(a["recall"]) else 0.0, "max_recall_colour": rmax,
            "precision_at_recall": {str(r): {"shape": precision_at(a, r), "colour": precision_at(b, r)} for r in levels},
            "precision_at_colour_max_recall": {"recall": rmax, "shape": precision_at(a, rmax) if rmax > 0 else None,
                                               "colour": precision_at(b, rmax) if rmax > 0 else None},
            "_curves": (a, b)}
    return res


def plot_pr(res: dict, path: Path, title: str) -> None:
    from testbed.plots import plt, save

    fig, axes = plt.subplots(2, 3, figsize=(11, 6.5))
    for ax, c in zip(axes.ravel(), CLASSES):
        a, b = res["classes"][c]["_curves"]
        ax.plot(a["recall"], a["precision"], "b-", lw=1.2, label=f"HOG (AP {100 * a['ap']:.1f})")
        ax.plot(b["recall"], b["precision"], "r-", lw=1.2, label=f"HOG + colour names (AP {100 * b['ap']:.1f})")
        ax.set_title(f"{c} ({a['positives']} objects)", fontsize=9)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall", fontsize=8)
        ax.set_ylabel("precision", fontsize=8)
        ax.legend(fontsize=7, loc="lower left")
    fig.suptitle(title, fontsize=10)
    save(fig, path)


def run_eval(out: Path, data_dir: Path = DEFAULT_DATA, max_images: int | None = None, streams: bool = True) -> dict:
    from testbed.io import write_json

    _, test_shards = shard_split(data_dir)
    if not test_shards:  # before the streams are built: they take minutes
        raise InputError(f"{data_dir}: no held-out data shards (every fifth: shard_00004, shard_00009, ... .npz + "
                         ".json); generate them with `dopeslam datagen`")
    out.mkdir(parents=True, exist_ok=True)
    det = HogDetector.load()
    sets = {"heldout_shards": load_shard_images(data_dir, test_shards, CLASSES)}
    if streams:
        sets["scenario_streams"] = test_images_from_streams()
    report = {"protocol": {"iou": IOU, "difficult": f"box < {MIN_BOX_H:.0f} px tall or < {MIN_VISIBLE:.0%} visible",
                           "test_shards": test_shards}, "sets": {}}
    for name, images in sets.items():
        if max_images:
            images = images[:max_images]
        res = evaluate(det, images, name)
        plot_pr(res, out / f"pr_{name}.png", f"Precision-recall, {name} ({len(images)} images)")
        for c in CLASSES:
            res["classes"][c].pop("_curves")
        summarise(res)
        report["sets"][name] = res
    write_json(out / "detector.json", report)
    return report


def summarise(res: dict) -> dict:
    """Mean APs and, at recall 0.25 and 0.5, the classes whose precision the colour step raises."""
    cls = res["classes"]
    res["mean_ap_shape"] = float(np.mean([cls[c]["ap_shape"] for c in CLASSES]))
    res["mean_ap_colour"] = float(np.mean([cls[c]["ap_colour"] for c in CLASSES]))
    res["colour_raises_precision_at_equal_recall"] = {}
    for r in ("0.25", "0.5"):
        res["colour_raises_precision_at_equal_recall"][r] = [
            c for c in CLASSES if (cls[c]["precision_at_recall"][r]["colour"] or 0)
            > (cls[c]["precision_at_recall"][r]["shape"] or 0) + 1e-9]
    return res


def print_table(report: dict) -> None:
    for name, res in report["sets"].items():
        print(f"{name}: {res['images']} images, {1000 * res['seconds_per_image']:.0f} ms per image")
        print(f"{'class':<12} {'objects':>7} {'AP shape':>9} {'AP +colour':>10} {'P@R.25 shape':>12} {'colour':>7} "
              f"{'P@R.5 shape':>11} {'colour':>7}")
        fmt = lambda v: "-" if v is None else f"{100 * v:.1f}"  # noqa: E731
        for c, r in res["classes"].items():
            q, h = r["precision_at_recall"]["0.25"], r["precision_at_recall"]["0.5"]
            print(f"{c:<12} {r['positives']:>7} {100 * r['ap_shape']:>9.1f} {100 * r['ap_colour']:>10.1f} "
                  f"{fmt(q['shape']):>12} {fmt(q['colour']):>7} {fmt(h['shape']):>11} {fmt(h['colour']):>7}")
        up = res["colour_raises_precision_at_equal_recall"]
        print(f"mean AP: shape {100 * res['mean_ap_shape']:.1f}, with colour {100 * res['mean_ap_colour']:.1f}; "
              f"the colour step raises precision at recall 0.25 for {len(up['0.25'])}/6, at recall 0.5 for {len(up['0.5'])}/6")


def run_args(args) -> int:
    """``dopeslam hog-detector train|eval|table`` (options: ``testbed/commands/topomap.py``)."""
    data = DEFAULT_DATA if getattr(args, "data", None) is None else args.data
    if args.hog_command == "table":
        def printer(report: dict) -> None:
            for res in report["sets"].values():
                summarise(res)
            print_table(report)

        print_saved_report(args.report, str(args.report), "an evaluation report (JSON) of dopeslam hog-detector eval",
                           printer)
        return 0
    if args.hog_command == "train":
        print(json.dumps(train(data, max_images=args.max_images, seed=args.seed, mining_rounds=args.mining_rounds,
                               mining_images=args.mining_images), indent=1))
    else:
        print_table(run_eval(args.out, data, args.max_images, not args.no_streams))
    return 0
