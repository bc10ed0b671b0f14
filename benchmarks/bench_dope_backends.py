"""DOPE network backends side by side: torch, ONNX Runtime, torch.compile; CPU time per image and differences.

A few 640x480 frames are rendered with the simulator (the scene of ``bench_dope.py``: E, Mustard and
Cookies at 0.8-1.5 m, seen from several camera poses), turned into the detector's 320x240 network input,
and run through the DOPE network (all stages) by every backend, interleaved round by round so that the
load of the machine falls on all of them alike. Reported per backend and thread count:

- ms per image: process CPU time of one forward pass (the network only), best and median of ``--repeats``;
- the largest absolute difference from torch (no_grad, the network as trained) of the belief maps and of
  the affinity fields, over every stage and every frame;
- whether ``DopeDetector.detect_stages`` (stage counts 1..S: peaks, association, PnP, depth fit, FPR,
  colour check) decodes the same detections from that backend's maps on every frame: same classes,
  FPR verdicts and key-point counts, key points within 1e-3 px (the largest key-point and translation
  differences are printed);
- first use: wall seconds to make the backend ready (ONNX export + session, or the compilation).

Backends:

- ``torch``: eager, ``torch.no_grad``, the network as trained (``DopeDetector(fold_stages=False,
  channels_last=False)``);
- ``torch channels-last``: ``inference_mode``, weights and input channels-last;
- ``torch channels-last folded``: the same with the refinement stages folded
  (``stack.dope.net.FoldedDopeNet``): as the detector runs it by default on a CPU with AVX-512;
- ``torch channels-last folded, refinement contiguous``: the same with the refinement stages (7x7
  convolutions) in the plain memory order (``stack.dope.net.set_memory_order``): as the detector runs it by
  default on an AVX2 CPU (``detector.refinement_order`` auto);
- ``torch channels-last bf16``: as ``DopeDetector(precision="bf16")`` runs it (folded), weights and input
  in bfloat16; only on a CPU with native bfloat16 (AVX512-BF16 or AMX);
- ``torch int8``: as ``DopeDetector(precision="int8")`` runs it (folded, its convolution blocks quantised
  at the calibration beside the weights: ``stack.dope.int8``); only where PyTorch has its x86 quantised
  kernels and the weights have a calibration;
- ``onnxruntime``: the network exported with ``torch.onnx.export(..., dynamo=False)`` (opset 17, batch,
  height and width free) to a temporary folder and run by ONNX Runtime's CPUExecutionProvider, every graph
  optimisation on, idle threads sleeping; ``onnxruntime spin`` lets them spin-wait (ONNX Runtime's
  default). Needs ``pip install onnxruntime onnx``;
- ``torch.compile``: inductor, compiled and timed at one thread only; skipped with ``--no-compile`` or
  when compiling fails. Its first use depends on inductor's cache (``TORCHINDUCTOR_CACHE_DIR``): minutes
  when cold, seconds when an earlier run left it warm.

    python benchmarks/bench_dope_backends.py [--repeats 30] [--frames 4] [--stages 6] [--threads 1,2]
        [--input rgb|depth] [--weights W] [--no-compile] [--json out.json]
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

OPSET = 17


class _Flat(torch.nn.Module):
    """DopeNet with ``stages`` stages, its outputs as one flat tuple (what the ONNX exporter takes)."""

    def __init__(self, model, stages: int):
        super().__init__()
        self.model, self.stages = model, int(stages)

    def forward(self, x):
        out = []
        for b, a in self.model(x, self.stages):
            out += [b, a]
        return tuple(out)


def export_onnx(model, stages: int, path, input_size=(320, 240)) -> Path:
    """``model`` with ``stages`` stages as an ONNX graph (batch, height and width free). torch 2.13's
    TorchScript exporter (``dynamo=False``) needs only the ``onnx`` package; the default dynamo exporter
    would also need ``onnxscript``."""
    import warnings

    w, h = input_size
    names = [f"{kind}{i}" for i in range(1, stages + 1) for kind in ("belief", "affinity")]
    axes = {"x": {0: "n", 2: "h", 3: "w"}, **{n: {0: "n", 2: "h8", 3: "w8"} for n in names}}
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(_Flat(model, stages), (torch.zeros(1, model.config.in_channels, h, w),), str(path),
                          input_names=["x"], output_names=names, dynamic_axes=axes, opset_version=OPSET, dynamo=False)
    return Path(path)


def ort_session(path, threads: int, spinning: bool):
    """ONNX Runtime on the CPU, every graph optimisation on (ORT_ENABLE_ALL: 10-20 % faster than EXTENDED
    here), ``threads`` intra-op threads that spin-wait when idle or sleep."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.intra_op_num_threads, so.inter_op_num_threads = int(threads), 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


POSES = ((0.0, 0.0), (0.15, 0.12), (-0.1, -0.15), (0.3, 0.05), (0.05, 0.25), (-0.2, 0.1))  # (forward m, yaw rad)


def render_frames(n: int):
    """``n`` (info, rgb, depth) of bench_dope.py's scene from different camera poses, and the class dims."""
    import pybullet as p

    from sim.camera import default_camera_info, new_client, render_rgbd

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_dope import build_scene

    client, _ = new_client("tiny")
    cat = build_scene(client)
    info = default_camera_info()
    rng = np.random.default_rng(0)
    frames = []
    for k in range(n):
        fwd, yaw = POSES[k % len(POSES)]
        c, s = np.cos(yaw), np.sin(yaw)
        R_world_body = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        T = np.eye(4)
        T[:3, :3] = R_world_body @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # optical: z forward
        T[:3, 3] = [fwd, 0, 0.3]
        rgb, depth, _ = render_rgbd(client, T, info, rng=rng, segmentation=False)
        frames.append((info, rgb, depth))
    p.disconnect(client)
    return frames, {c: s.dims for c, s in cat.items()}


def cpu_ms(fn) -> float:
    c0 = time.process_time()
    fn()
    return 1000.0 * (time.process_time() - c0)


def compare_detections(ref: dict, got: dict) -> tuple[bool, int, float, float]:
    """(identical, detections, max key-point difference px, max translation difference mm) over stage counts."""
    same, n, dkp, dt = True, 0, 0.0, 0.0
    for s, dets in ref.items():
        other = got[s]
        n += len(dets)
        if len(dets) != len(other):
            same = False
            continue
        for a, b in zip(dets, other):
            fa, fb = np.isfinite(a.keypoints_px[:, 0]), np.isfinite(b.keypoints_px[:, 0])
            if a.cls != b.cls or a.fpr_pass != b.fpr_pass or not np.array_equal(fa, fb):
                same = False
                continue
            dkp = max(dkp, float(np.abs(a.keypoints_px[fa] - b.keypoints_px[fb]).max(initial=0.0)))
            dt = max(dt, 1000.0 * float(np.abs(a.T_cam_obj[:3, 3] - b.T_cam_obj[:3, 3]).max()))
    return same and dkp < 1e-3, n, dkp, dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30, help="timed passes per backend (frames taken in turn)")
    ap.add_argument("--frames", type=int, default=4, help="rendered frames (differences and detections on all)")
    ap.add_argument("--stages", type=int, default=6)
    ap.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    ap.add_argument("--input", choices=("rgb", "depth"), default="rgb")
    ap.add_argument("--weights", default=None)
    ap.add_argument("--no-compile", action="store_true", help="skip torch.compile")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    threads = [int(t) for t in args.threads.split(",") if t.strip()]

    notes = []
    try:
        import onnx  # noqa: F401  (torch's exporter needs it)
        import onnxruntime
        ort_version = onnxruntime.__version__
    except ModuleNotFoundError as exc:
        ort_version = None
        notes.append(f"onnxruntime skipped: {exc.name} is not installed (pip install onnxruntime onnx)")
    from stack.dope.net import FoldedDopeNet, set_memory_order
    from stack.dope_fpr import DopeDetector, bf16_native
    from stack.messages import CameraFrame

    torch.set_num_threads(1)
    raw, dims = render_frames(args.frames)
    frames = [CameraFrame(0.1 * i, info, rgb=rgb, depth_m=depth) for i, (info, rgb, depth) in enumerate(raw)]
    det = DopeDetector(weights=args.weights, input=args.input, stages=args.stages, dims=dims, threads=1,
                       precision="fp32", fold_stages=False, channels_last=False)  # the reference: as trained
    model, S = det.model, args.stages
    inputs = [det._inputs(f)[0] for f in frames]
    inputs = [x for x in inputs if len(x)]
    if not inputs:
        raise SystemExit("no network input in the rendered frames (depth windows all empty?)")

    @torch.no_grad()
    def torch_fn(x):
        return [(b.numpy(), a.numpy()) for b, a in model(torch.from_numpy(x), S)]

    model_cl = copy.deepcopy(model).to(memory_format=torch.channels_last)

    @torch.inference_mode()
    def channels_last_fn(x):
        xt = torch.from_numpy(x).contiguous(memory_format=torch.channels_last)
        return [(b.numpy(), a.numpy()) for b, a in model_cl(xt, S)]

    model_folded = FoldedDopeNet(copy.deepcopy(model)).to(memory_format=torch.channels_last)

    @torch.inference_mode()
    def folded_fn(x):  # as DopeDetector runs it by default
        xt = torch.from_numpy(x).contiguous(memory_format=torch.channels_last)
        return [(b.numpy(), a.numpy()) for b, a in model_folded(xt, S)]

    model_mixed = set_memory_order(FoldedDopeNet(copy.deepcopy(model)), True, False)

    @torch.inference_mode()
    def mixed_fn(x):  # as DopeDetector runs it by default on an AVX2 CPU (refinement_order auto)
        xt = torch.from_numpy(x).contiguous(memory_format=torch.channels_last)
        return [(b.numpy(), a.numpy()) for b, a in model_mixed(xt, S)]

    model_bf16 = copy.deepcopy(model_folded).to(torch.bfloat16)

    @torch.inference_mode()
    def bf16_fn(x):  # as DopeDetector(precision="bf16") runs it
        xt = torch.from_numpy(x).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
        return [(b.float().numpy(), a.float().numpy()) for b, a in model_bf16(xt, S)]

    from stack.dope import int8

    int8_det = None
    if int8.available():
        try:
            int8_det = DopeDetector(weights=args.weights, input=args.input, stages=args.stages, dims=dims, threads=1,
                                    precision="int8")
        except int8.Int8Error as exc:
            notes.append(f"int8 skipped: {exc}")
    else:
        notes.append("int8 skipped: this PyTorch has no x86 quantised kernels")

    @torch.inference_mode()
    def int8_fn(x):  # as DopeDetector(precision="int8") runs it
        return [(b.numpy(), a.numpy()) for b, a in int8_det.model(torch.from_numpy(x), S)]

    cache = tempfile.TemporaryDirectory(prefix="dope-onnx-")
    if ort_version:
        t0 = time.perf_counter()
        onnx_file = export_onnx(model, S, Path(cache.name) / "dope.onnx", det.input_size)
        export_s = time.perf_counter() - t0
    backends = []  # (name, threads, fn, first-use wall s)
    for th in threads:
        backends.append(("torch", th, torch_fn, 0.0))
        backends.append(("torch channels-last", th, channels_last_fn, 0.0))
        backends.append(("torch channels-last folded", th, folded_fn, 0.0))
        backends.append(("torch channels-last folded, refinement contiguous", th, mixed_fn, 0.0))
        if bf16_native():
            backends.append(("torch channels-last bf16", th, bf16_fn, 0.0))
        if int8_det is not None:
            backends.append(("torch int8", th, int8_fn, 0.0))
        for spin in ((False, True) if th > 1 else (False,)) if ort_version else ():
            t0 = time.perf_counter()
            sess = ort_session(onnx_file, th, spin)

            def ort_fn(x, sess=sess):
                out = sess.run(None, {"x": x})
                return [(out[2 * i], out[2 * i + 1]) for i in range(S)]

            ort_fn(inputs[0])
            backends.append(("onnxruntime" + (" spin" if spin else ""), th, ort_fn, export_s + time.perf_counter() - t0))
    if not args.no_compile and 1 in threads:
        try:
            t0 = time.perf_counter()
            compiled = torch.compile(model, dynamic=False)

            @torch.no_grad()
            def compiled_fn(x, cm=compiled):
                return [(b.numpy(), a.numpy()) for b, a in cm(torch.from_numpy(x), S)]

            compiled_fn(inputs[0])
            backends.append(("torch.compile", 1, compiled_fn, time.perf_counter() - t0))
        except Exception as exc:  # a C compiler or inductor problem: report and go on without it
            traceback.print_exc()
            notes.append(f"torch.compile skipped: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")

    # differences from torch, on every frame's input
    refs = [torch_fn(x) for x in inputs]
    diffs = {}
    for name, th, fn, _ in backends:
        db = da = 0.0
        for x, ref in zip(inputs, refs):
            for (b, a), (rb, ra) in zip(fn(x), ref):
                db, da = max(db, float(np.abs(b - rb).max())), max(da, float(np.abs(a - ra).max()))
        diffs[(name, th)] = (db, da)

    # timing: per thread count, the backends interleaved round by round
    times = {(name, th): [] for name, th, _, _ in backends}
    for th in threads:
        torch.set_num_threads(th)
        group = [b for b in backends if b[1] == th]
        for _, _, fn, _ in group:
            fn(inputs[0])  # warm-up at this thread count
        for r in range(args.repeats):
            x = inputs[r % len(inputs)]
            for name, _, fn, _ in group:
                times[(name, th)].append(cpu_ms(lambda: fn(x)))
    torch.set_num_threads(1)
    load = os.getloadavg()

    # detections decoded from each backend's maps, against torch's
    ref_dets = [det.detect_stages(f) for f in frames]
    rows = []
    for name, th, fn, first in backends:
        det._forward = lambda x, s, fn=fn: fn(x)[:s]
        got = [det.detect_stages(f) for f in frames]
        res = [compare_detections(r, g) for r, g in zip(ref_dets, got)]
        del det._forward
        t = times[(name, th)]
        rows.append({"backend": name, "threads": th, "best_ms": min(t), "median_ms": float(np.median(t)),
                     "belief_diff": diffs[(name, th)][0], "affinity_diff": diffs[(name, th)][1],
                     "identical": all(r[0] for r in res), "detections": sum(r[1] for r in res),
                     "keypoint_diff_px": max(r[2] for r in res), "translation_diff_mm": max(r[3] for r in res),
                     "first_use_s": first})
    cache.cleanup()
    if not bf16_native():
        notes.append("bf16 skipped: this CPU has no native bfloat16 (AVX512-BF16 or AMX)")

    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {args.input} input 320x240, {S} stages, "
          f"{len(frames)} frames, {args.repeats} passes per backend; torch {torch.__version__}, "
          f"onnxruntime {ort_version or '-'}" + ("; depth: a pass is all windows of a frame" if args.input == "depth" else ""))
    print()
    print("| backend | threads | ms per image, best | median | vs torch (median) | max diff belief | max diff affinity "
          "| same detections | first use (s) |")
    print("|---|---:|---:|---:|---:|---:|---:|---|---:|")
    base = {r["threads"]: r["median_ms"] for r in rows if r["backend"] == "torch"}
    for r in rows:
        rel = f"{100.0 * (r['median_ms'] / base[r['threads']] - 1):+.0f} %" if r["threads"] in base else ""
        same = (f"{'yes' if r['identical'] else 'NO'} ({r['detections']} dets, kp {r['keypoint_diff_px']:.1e} px, "
                f"t {r['translation_diff_mm']:.1e} mm)")
        zero = r["backend"] == "torch" and r["belief_diff"] == 0 and r["affinity_diff"] == 0
        db, da = ("-", "-") if zero else (f"{r['belief_diff']:.1e}", f"{r['affinity_diff']:.1e}")
        print(f"| {r['backend']} | {r['threads']} | {r['best_ms']:.1f} | {r['median_ms']:.1f} | {rel} | {db} | {da} | "
              f"{same} | {r['first_use_s']:.1f} |")
    for note in notes:
        print(f"\n{note}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"load_average": list(load), "rows": rows, "notes": notes}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
