"""``dopeslam datagen`` (synthetic DOPE training data) and ``dopeslam train`` (train / resume DOPE)."""
from __future__ import annotations

import json
import logging
import math

from stack.errors import UsageError

log = logging.getLogger(__name__)


def _datagen(args) -> int:
    from pathlib import Path

    from sim.datagen import DatagenConfig, generate
    from testbed import progress

    if not 0.0 <= args.slim_stand_prob <= 1.0:
        raise UsageError(f"--slim-stand-prob: expected a share from 0 to 1, got {args.slim_stand_prob}")
    for option, value, low in (("--images", args.images, 1), ("--shard-size", args.shard_size, 1),
                               ("--workers", args.workers, 1), ("--width", args.width, 32), ("--height", args.height, 24)):
        if value < low:
            raise UsageError(f"{option}: expected at least {low}, got {value}")
    cfg = DatagenConfig(out_dir=Path(args.out), n_images=args.images, shard_size=args.shard_size, seed=args.seed,
                        workers=args.workers, width=args.width, height=args.height,
                        slim_stand_prob=args.slim_stand_prob)
    paths = generate(cfg, progress=progress.enabled())
    print(f"{len(paths)} shards ({args.images} images) in {args.out}")
    return 0


def parse_class_weights(items) -> dict:
    """``["Yogurt=3", ...]`` -> ``{"Yogurt": 3.0}``; a malformed item names the flag and the form expected."""
    from stack.dope.train import TrainConfig

    classes = list(TrainConfig.__dataclass_fields__["classes"].default)
    out = {}
    for item in items or []:
        cls, sep, w = item.partition("=")
        try:
            weight = float(w)
        except ValueError:
            weight = -1.0
        if not sep or cls not in classes or weight <= 0:
            raise UsageError(f"--class-weight: expected CLASS=WEIGHT with CLASS one of {classes} and WEIGHT > 0, "
                             f"got {item!r}")
        out[cls] = weight
    return out


def _train(args) -> int:
    from stack.dope.train import TrainConfig, train

    window = _numbers(args.depth_window, "--depth-window", "NEAR,FAR metres with 0 <= NEAR < FAR", 2,
                      lambda v: 0 <= v[0] < v[1]) if args.depth_window else (0.0, 0.0)
    decay = _numbers(args.lr_decay, "--lr-decay", "step numbers such as 5000,8000", None,
                     lambda v: all(x >= 1 and x == int(x) for x in v)) if args.lr_decay else ()
    for option, value, ok, expected in (
            ("--batch", args.batch, args.batch >= 1, "at least 1"),
            ("--crop", args.crop, args.crop >= 32 and args.crop % 8 == 0, "a multiple of 8, at least 32"),
            ("--lr", args.lr, math.isfinite(args.lr) and args.lr > 0, "a number > 0"),
            ("--width", args.width, math.isfinite(args.width) and args.width > 0, "a multiplier > 0"),
            ("--stages", args.stages, args.stages >= 1, "at least 1"),
            ("--steps", args.steps, args.steps >= 1, "at least 1"),
            ("--minutes", args.minutes, args.minutes > 0, "a number > 0")):
        if not ok:
            raise UsageError(f"{option}: expected {expected}, got {value}")
    cfg = TrainConfig(data_dir=args.data, out_dir=args.out, input=args.input, width=args.width, stages=args.stages,
                      batch=args.batch, crop=(args.crop, args.crop), lr=args.lr, max_steps=args.steps,
                      max_minutes=args.minutes, checkpoint_minutes=args.checkpoint_minutes, seed=args.seed,
                      init_from=args.init_from or "", depth_window=window, threads=args.threads,
                      class_weights=parse_class_weights(args.class_weight),
                      lr_decay_steps=tuple(int(v) for v in decay))
    summary = train(cfg)
    print(json.dumps(summary, indent=1))
    return 0


def _detector(args):
    from sim.objects import load_catalog
    from stack.dope_fpr import DopeDetector

    dims = {c: s.dims for c, s in load_catalog().items()}
    return DopeDetector(weights=args.weights or None, input=args.input, stages=6, fpr=True, dims=dims,
                        thresholds=getattr(args, "thresholds", None) or None,
                        depth_refine=not args.no_depth_refine, precision=getattr(args, "precision", "fp32"))


def _numbers(text: str, option: str, expected: str, count: int | None, ok) -> tuple[float, ...]:
    """``text``'s comma-separated numbers (``count`` of them, None: one or more) for which ``ok`` holds,
    else a UsageError naming ``option``."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if not values or (count is not None and len(values) != count) or not all(map(math.isfinite, values)) \
            or not ok(values):
        raise UsageError(f"{option}: expected {expected}, got {text!r}")
    return values


def _shards(args) -> list[int]:
    if args.shards:
        a, sep, b = args.shards.partition(":")
        if not (sep and a.strip().isdigit() and b.strip().isdigit() and int(a) < int(b)):
            raise UsageError(f"--shards: expected A:B, shard numbers with A < B (e.g. 0:2), got {args.shards!r}")
        return list(range(int(a), int(b)))
    return [0, 1]  # the training run's held-out shards


def _evaluate(args) -> int:
    from stack.dope.evaluate import evaluate
    from testbed import progress

    det = _detector(args)
    res = evaluate(det, args.data, _shards(args), progress=progress.enabled())
    table = res["per_stages"]
    print(f"{res['images']} images from {args.data}, weights {det.weights_path}, network {det.precision}")
    print("stages  instances  detected  det(FPR)  median pos err  ADD pass  precision  precision(FPR)")
    for s, r in table.items():
        pe = "n/a" if r["median_position_error_m"] is None else f"{100 * r['median_position_error_m']:.1f} cm"
        print(f"{s:>6}  {r['instances']:>9}  {100 * r['detection_rate']:7.1f}%  {100 * r['detection_rate_fpr']:7.1f}%"
              f"  {pe:>14}  {100 * r['add_pass_rate']:7.1f}%  {100 * r['precision']:8.1f}%  {100 * r['precision_fpr']:12.1f}%")
    if args.out:
        from testbed.io import write_json

        write_json(args.out, {"weights": str(det.weights_path), "input": args.input, "precision": det.precision,
                              "data": args.data, "shards": _shards(args), "per_stages": table}, indent=1)
    return 0


def _calibrate(args) -> int:
    from stack.dope.evaluate import evaluate
    from stack.dope_fpr import FprThresholds, file_sha256
    from testbed import progress

    det = _detector(args)
    det.fpr = False
    res = evaluate(det, args.data, _shards(args), progress=progress.enabled())
    th = FprThresholds.calibrate(res["records"], args.target_precision, min_recall=args.min_recall,
                                 fallback_recall=args.fallback_recall,
                                 meta={"weights_sha256": file_sha256(det.weights_path), "data": args.data,
                                       "shards": _shards(args), "input": args.input, "precision": det.precision})
    th.save(args.out)
    for cls, row in th.meta["stats"].items():
        print(cls, {s: (round(v["threshold"], 2), round(v["precision"], 3), round(v["recall"], 3), v["n"])
                    for s, v in row.items()})
    print(f"thresholds written to {args.out}")
    return 0


def _calibrate_int8(args) -> int:
    import torch

    from stack.dope import int8
    from stack.dope.evaluate import load_shard_frames
    from stack.dope.train import ShardData
    from stack.dope_fpr import file_sha256
    from stack.errors import InputDataError

    det = _detector(args)
    out = args.out or str(int8.calibration_path(det.weights_path))
    shards = _shards(args) if args.shards else ShardData(args.data, det.classes).available()
    if not shards:
        raise InputDataError(f"{args.data}: no shard_*.npz/.json pairs (run `dopeslam datagen` first)")

    def batches():
        for frame, _ in load_shard_frames(args.data, shards, det.classes):
            x, _ = det._inputs(frame)
            if len(x):
                yield torch.from_numpy(x)

    cal = int8.calibrate(det.model.to(memory_format=torch.contiguous_format), batches(),
                         meta={"weights_sha256": file_sha256(det.weights_path), "input": args.input,
                               "data": args.data, "shards": shards})
    int8.save(out, cal)
    print(f"int8 calibration from {cal['inputs']} network inputs ({len(cal['blocks'])} blocks) written to {out}")
    return 0


def _export(args) -> int:
    from stack.dope.net import expand_stages, load_weights, save_weights

    model, extra = load_weights(args.src)
    if args.stages and args.stages != model.config.stages:
        extra["trained_stages"] = model.config.stages
        model = expand_stages(model, args.stages)
    extra.update({"source": str(args.src)})
    save_weights(args.out, model, half=True, extra=extra)
    print(f"{args.out}: {model.config.stages} stages, width {model.config.width}, classes {list(model.classes)}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("datagen", help="render synthetic DOPE training data (RGB, depth, segmentation, cuboid annotations)")
    p.add_argument("--out", required=True, help="output directory for shard_NNNNN.npz/.json")
    p.add_argument("--images", type=int, default=4000)
    p.add_argument("--shard-size", type=int, default=50)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--slim-stand-prob", type=float, default=0.5,
                   help="share of objects on stands that stand on a slim one, as in the scenarios (0 reproduces "
                        "the data of the RGB weights and of the first depth weights)")
    p.set_defaults(func=_datagen)

    t = subparsers.add_parser("train", help="train (or resume) the DOPE network on datagen shards")
    t.add_argument("--data", required=True, help="directory of datagen shards")
    t.add_argument("--out", required=True, help="run directory (checkpoint.pt, weights_fp16.pt, loss.png, evals.json)")
    t.add_argument("--input", choices=("rgb", "depth"), default="rgb")
    t.add_argument("--width", type=float, default=0.25, help="channel width multiplier")
    t.add_argument("--stages", type=int, default=6)
    t.add_argument("--batch", type=int, default=8)
    t.add_argument("--crop", type=int, default=128, help="square training crop, input pixels (multiple of 8)")
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--lr-decay", default="5000,8000", help="steps at which the learning rate is multiplied by 0.3")
    t.add_argument("--steps", type=int, default=1_000_000)
    t.add_argument("--minutes", type=float, default=1e9, help="stop after this much wall time")
    t.add_argument("--checkpoint-minutes", type=float, default=5.0)
    t.add_argument("--init-from", default="", help="weights to start from (e.g. the RGB weights for the depth net)")
    t.add_argument("--depth-window", default="", help="near,far metres (depth input; default: around a random object)")
    t.add_argument("--threads", type=int, default=0)
    t.add_argument("--class-weight", action="append", default=[], metavar="CLASS=W",
                   help="pick crops centred on CLASS W times as often (repeatable; e.g. Yogurt=3 for a class "
                        "the network misses)")
    t.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=_train)

    x = subparsers.add_parser("dope-export", help="export run weights (half precision, optionally expanded to more stages)")
    x.add_argument("--src", required=True, help="weights_fp16.pt of a training run")
    x.add_argument("--out", required=True, help="e.g. stack/weights/dope_rgb.pt")
    x.add_argument("--stages", type=int, default=6, help="repeat the last trained stage up to this many stages")
    x.set_defaults(func=_export)

    for name, func, helptext in (("dope-eval", _evaluate, "DOPE accuracy per stage count on held-out datagen shards"),
                                 ("calibrate-fpr", _calibrate, "calibrate FPR belief-sum thresholds per class and stage count"),
                                 ("calibrate-int8", _calibrate_int8,
                                  "calibrate the network's int8 activation scales (precision = int8) on datagen shards")):
        e = subparsers.add_parser(name, help=helptext)
        e.add_argument("--data", required=True, help="directory of datagen shards")
        e.add_argument("--shards", default="", help="A:B shard index range (default: " + (
            "every shard" if name == "calibrate-int8" else "the held-out shards 0:2") + ")")
        e.add_argument("--weights", default="", help="weights file (default: shipped for --input)")
        e.add_argument("--input", choices=("rgb", "depth"), default="rgb")
        e.add_argument("--no-depth-refine", action="store_true",
                       help="report PnP-only poses (default: each pose is fitted along its ray to the aligned depth)")
        if name != "calibrate-int8":  # that one calibrates the float network
            e.add_argument("--precision", choices=("fp32", "bf16", "int8"), default="fp32",
                           help="the network's arithmetic, as the config's detector.precision")
        if name == "calibrate-fpr":
            e.add_argument("--target-precision", type=float, default=0.995)
            e.add_argument("--min-recall", type=float, default=0.6,
                           help="a cut meets the precision target only if it keeps this share of true detections")
            e.add_argument("--fallback-recall", type=float, default=0.95,
                           help="where the target is out of reach, keep this share of true detections")
            e.add_argument("--out", required=True, help="thresholds JSON (e.g. stack/weights/fpr_thresholds_rgb.json)")
        elif name == "calibrate-int8":
            e.add_argument("--out", default="", help="calibration JSON (default: NAME_int8.json beside the weights, "
                                                     "where precision = int8 looks for it)")
        else:
            e.add_argument("--thresholds", default="", help="FPR thresholds JSON (default: beside the weights)")
            e.add_argument("--out", default="", help="write the table as JSON")
        e.set_defaults(func=func)
