"""Where the main job's CPU goes, stage by stage, beside the floor each stage could reach on this CPU.

Runs one episode as ``dopeslam run --sequential`` does (RGB, 6 stages, FPR; the detector in the message
loop and the camera rendered in this process, so each stage's cost is counted alone) with a CPU-time meter (``time.process_time``: this process's CPU time, all its
threads, far less affected by other busy processes than wall time) around each stage:

- simulation: physics, the route follower, ground truth and the harness's own bookkeeping (the rest);
- rendering: the camera (PyBullet's renderer, RGB + depth + segmentation, then the D435i's noise);
- LiDAR: the analytic ray caster;
- odometry: ``stack.lidar_slam.LidarOdometry.process`` (KISS-ICP plus the floor fit);
- DOPE network: the forward pass;
- depth fit + FPR: input scaling, peak decoding, PnP, the depth fit, FPR and the colour check;
- fusion: the pipeline's fusion of detections into the map and the evidence gate.

The floors, measured on the same machine and the same data:

- rendering: ``p.getCameraImage`` alone for one frame at the camera's size (no noise, no copies),
  with and without the segmentation mask, times the camera rate; beside it, the same call at 16x12
  pixels: what a frame costs whatever its size (PyBullet's EGL renderer draws a 4096x4096 shadow map
  before every image, and a DIRECT client cannot switch it off);
- DOPE network: its FLOPs (``torch.utils.flop_counter``) per image at the faster of two GFLOP/s
  measured on this CPU in the network's precision with the same torch threads: a 1024^3 ``torch.mm``
  (fp32, or bf16 where the detector runs bf16) and the network's fastest convolution run alone on its
  own input (the convolution library can be twice as fast as the matmul library on the same CPU),
  times the network's inputs per second (one per image; with depth input, one per depth window). In
  int8 the operations are the float network's (the FLOP counter does not see quantised kernels) and
  the rate is the fastest int8 convolution module's alone, its operations counted from its shape (there
  is no int8 matmul to set beside it; a block of one convolution runs it as an operator, not a module,
  but its shape is among those of the blocks timed);
- odometry: KISS-ICP's own voxelisation, alignment and map update as the stack's odometry calls them,
  on the points it registers (deskewed, cropped, the floor left out: the floor fit holds height, roll
  and pitch); beside it, ``KissICP.register_frame`` on the same whole sweeps (the points the simulator
  gave) without and with its deskew, times the sweep rate.

    python benchmarks/bench_stages.py [--scenario NAME] [--duration S] [--seed N] [--profile full|fast]
        [--precision fp32|bf16|int8] [--set KEY=VALUE ...] [--png PATH]

``--set`` takes any config key, e.g. ``--set detector.keyframe_m=0.1 --set detector.keyframe_deg=5``
(the keyframe gate: the network on the images the gate lets through only). ``--png PATH`` also draws
the table as a bar chart, each stage's CPU time beside its floor.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

STAGES = ("simulation", "rendering", "lidar", "odometry", "network", "fit_fpr", "fusion")
LABELS = {"simulation": "simulation (physics, ground truth, harness)", "rendering": "rendering (RGB + depth (+ seg: full profile), noise)",
          "lidar": "LiDAR ray casting", "odometry": "KISS-ICP odometry (+ floor fit)", "network": "DOPE network",
          "fit_fpr": "depth fit + FPR (+ decode, PnP, colour check)", "fusion": "fusion + evidence"}


class Meter:
    """CPU seconds per stage; a stage's time excludes the stages metered inside it."""

    def __init__(self):
        self.cpu = dict.fromkeys(STAGES, 0.0)
        self.calls = dict.fromkeys(STAGES, 0)
        self._stack: list[list] = []  # [stage, start, inner seconds]

    def wrap(self, owner, name: str, stage: str) -> None:
        fn = getattr(owner, name)
        meter = self

        def timed(*a, **k):
            meter._stack.append([stage, time.process_time(), 0.0])
            try:
                return fn(*a, **k)
            finally:
                st, t0, inner = meter._stack.pop()
                dt = time.process_time() - t0
                meter.cpu[st] += dt - inner
                meter.calls[st] += 1
                if meter._stack:
                    meter._stack[-1][2] += dt

        timed.__wrapped__ = fn
        setattr(owner, name, timed)


def matmul_gflops(n: int = 1024, repeats: int = 5, precision: str = "fp32") -> float:
    """Best GFLOP/s of an n^3 matrix product (``precision`` fp32 or bf16) with torch's current thread
    count (CPU time)."""
    import torch

    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    torch.mm(a, b)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        torch.mm(a, b)
        best = min(best, time.process_time() - t0)
    return 2.0 * n ** 3 / max(best, 1e-9) / 1e9


def _is_conv(module) -> bool:
    """A 2-D convolution, float (``nn.Conv2d``) or quantised (``torch.ao.nn.quantized.Conv2d`` and its
    fused ReLU variant)."""
    import torch
    from torch.ao.nn.quantized import Conv2d as QuantizedConv2d

    return isinstance(module, (torch.nn.Conv2d, QuantizedConv2d))


def conv_flops(module, out) -> int:
    """FLOPs of one 2-D convolution from its shape and output ``out``: two per multiply-add, as
    ``torch.utils.flop_counter`` counts a convolution (the bias not counted)."""
    kh, kw = module.kernel_size
    return 2 * out.numel() * (module.in_channels // module.groups) * kh * kw


def conv_gflops(detector, repeats: int = 3) -> tuple[float, str]:
    """Best GFLOP/s (CPU time) of any one convolution of the detector's network run alone, on the very
    input it gets in one forward pass (the detector's precision and memory order, torch's current thread
    count), and that layer's shape: the rate the CPU's convolution kernels reach on this network's
    layers at their best. A CPU's matmul library and its convolution library can differ by 2x (on
    AVX-512 machines whose matmul path is tuned for AVX2), so the network's floor takes the faster."""
    import numpy as np
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    seen = {}

    def hook(mod, inputs, _out):
        x = inputs[0]
        key = (mod.in_channels, mod.out_channels, mod.kernel_size, mod.stride, tuple(x.shape))
        seen.setdefault(key, (mod, x.detach().clone(memory_format=torch.preserve_format)))

    hooks = [m.register_forward_hook(hook) for m in detector.model.modules() if _is_conv(m)]
    try:
        w, h = detector.input_size
        detector._forward(np.zeros((1, 3, h, w), dtype=np.float32), detector.stages, last_only=True)
    finally:
        for hk in hooks:
            hk.remove()
    best_rate, best_shape = 0.0, "-"
    with torch.inference_mode():
        for (cin, cout, k, _stride, shape), (mod, x) in seen.items():
            if isinstance(mod, torch.nn.Conv2d):
                with FlopCounterMode(display=False) as fc:
                    mod(x)
                flops = fc.get_total_flops()
            else:  # quantised: the counter does not see it
                flops = conv_flops(mod, mod(x))
            best = float("inf")
            for _ in range(repeats):
                t0 = time.process_time()
                mod(x)
                best = min(best, time.process_time() - t0)
            rate = flops / max(best, 1e-9) / 1e9
            if rate > best_rate:
                best_rate, best_shape = rate, f"{k[0]}x{k[1]} conv {cin}->{cout} at {shape[-1]}x{shape[-2]}"
    return best_rate, best_shape


def network_flops(detector) -> int:
    """FLOPs of one forward pass of the detector's network on one image at its input size. In int8 they are
    the float network's (the same multiply-adds; the FLOP counter does not see quantised kernels)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    if getattr(detector, "precision", "fp32") == "int8":
        from stack.dope_fpr import DopeDetector

        detector = DopeDetector(weights=detector.weights_path, input=detector.input, stages=detector.stages,
                                dims=detector.dims, input_size=detector.input_size, precision="fp32",
                                fold_stages=detector.fold_stages)
    w, h = detector.input_size
    x = torch.zeros(1, 3, h, w, dtype=next(detector.model.parameters()).dtype)
    with torch.no_grad():
        detector.model(x, detector.stages)  # what is computed once per image size is not counted per image
        with FlopCounterMode(display=False) as fc:
            detector.model(x, detector.stages)
    return int(fc.get_total_flops())


def render_floor(client: int, renderer: int, T_world_cam, info, repeats: int = 5) -> tuple[float, float, float]:
    """Best CPU seconds of ``getCameraImage`` alone for one frame: (with segmentation, without, and
    without at 16x12 pixels: the part of a frame's cost that does not grow with its size)."""
    import pybullet as p

    from sim.camera import gl_matrices

    view, proj = gl_matrices(T_world_cam, info)
    out = []
    for flags, (w, h) in ((0, (info.width, info.height)), (p.ER_NO_SEGMENTATION_MASK, (info.width, info.height)),
                          (p.ER_NO_SEGMENTATION_MASK, (16, 12))):
        best = float("inf")
        for _ in range(repeats):
            t0 = time.process_time()
            p.getCameraImage(w, h, view, proj, renderer=renderer, flags=flags, physicsClientId=client)
            best = min(best, time.process_time() - t0)
        out.append(best)
    return out[0], out[1], out[2]


def kiss_floor(scans, config) -> float:
    """CPU seconds per sweep of KISS-ICP's own ``register_frame`` on the same sweeps."""
    import numpy as np
    from kiss_icp.kiss_icp import KissICP

    icp = KissICP(config.to_kiss())
    t0 = time.process_time()
    for s in scans:
        ts = np.asarray(s.times_s, dtype=np.float64)
        span = float(np.ptp(ts)) if ts.size else 0.0
        icp.register_frame(np.asarray(s.points, dtype=np.float64), (ts - ts.min()) / span if span > 0 else ts)
    return (time.process_time() - t0) / max(len(scans), 1)


def measure(scenario=None, duration=None, seed=0, profile: str = "full", precision: str | None = None,
            sets: tuple[str, ...] = ()) -> dict:
    """``sets``: config keys (``KEY=VALUE``) over the shipped config; ``precision`` is one more."""
    os.environ.setdefault("DOPESLAM_RENDER_WORKER", "0")  # render here, so the rendering's CPU is counted
    from sim.episode import Episode
    from stack.dope_fpr import DopeDetector
    from stack.lidar_slam import LidarOdometry
    from stack.pipeline import DopeSlam
    from testbed.run import run_episode

    meter = Meter()
    scans, frames, handles, inputs = [], [], {}, []
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration

    # KISS-ICP's own voxelisation, alignment and map update, on exactly the points the stack's odometry
    # registers (deskewed, cropped, the floor left out): the odometry's floor. A meter of their own, so
    # the odometry stage keeps counting them.
    kiss_core, kiss_calls = Meter(), ((KissICP, "voxelize"), (Registration, "align_points_to_map"),
                                      (VoxelHashMap, "update"))
    for owner, name in kiss_calls:
        kiss_core.wrap(owner, name, "odometry")
    meter.wrap(Episode, "_camera_frame", "rendering")
    meter.wrap(Episode, "_lidar_scan", "lidar")
    meter.wrap(LidarOdometry, "process", "odometry")
    meter.wrap(DopeDetector, "_forward", "network")
    meter.wrap(DopeDetector, "detect", "fit_fpr")
    meter.wrap(DopeSlam, "_fuse_image", "fusion")
    orig_close, orig_process, orig_detect, orig_forward = (Episode.close, LidarOdometry.process, DopeDetector.detect,
                                                           DopeDetector._forward)

    def close(self):  # the floors are measured on the episode's own world before it goes
        if "floors" not in handles and "frame" in handles:
            f = handles["frame"]
            handles["floors"] = render_floor(self.client, self.renderer, f.T_world_camera, f.info)
            handles["camera_rate"] = self.camera_rate
            handles["lidar_rate"] = 1.0 / self.beams.period
        return orig_close(self)

    def process(self, scan):
        scans.append(scan)
        handles.setdefault("odom_config", self.config)
        return orig_process(self, scan)

    def detect(self, frame):
        frames.append(frame.stamp)
        if len(frames) & (len(frames) - 1) == 0:  # the last power-of-two'th: in the episode's second half
            handles["frame"] = frame
        handles.setdefault("detector", self)
        return orig_detect(self, frame)

    def forward(self, x, *a, **k):  # the network's inputs: one per image, or a few depth windows per image
        inputs.append(len(x))
        return orig_forward(self, x, *a, **k)

    Episode.close, LidarOdometry.process, DopeDetector.detect, DopeDetector._forward = close, process, detect, forward
    try:
        with tempfile.TemporaryDirectory() as tmp:
            w0, c0 = time.perf_counter(), time.process_time()
            config = None
            sets = [*sets, *([f"detector.precision={precision}"] if precision is not None else [])]
            if sets:  # the shipped config with these keys set
                from stack.config import resolve_config
                from testbed.settings import RunConfig

                config = resolve_config(sets=sets, model=RunConfig)
            r = run_episode(scenario, out_dir=tmp, seed=seed, duration=duration, write_outputs=False, profile=profile,
                            sequential=True, config=config)  # one stage at a time: the meter's CPU deltas are each stage's own
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    finally:
        Episode.close, LidarOdometry.process, DopeDetector.detect, DopeDetector._forward = \
            orig_close, orig_process, orig_detect, orig_forward
        for owner, name in ((Episode, "_camera_frame"), (Episode, "_lidar_scan"), (LidarOdometry, "process"),
                            (DopeDetector, "_forward"), (DopeDetector, "detect"), (DopeSlam, "_fuse_image"),
                            *kiss_calls):
            setattr(owner, name, getattr(owner, name).__wrapped__)
    sim_s = float(r["sim_seconds"])
    meter.cpu["simulation"] = cpu - sum(v for k, v in meter.cpu.items() if k != "simulation")
    det = handles.get("detector")
    floors = {}
    if "floors" in handles:
        seg, noseg, tiny = (v * handles["camera_rate"] for v in handles["floors"])
        floors["rendering"] = (seg, noseg, tiny)
        if profile == "fast":  # no segmentation image rendered: its floor is the one without
            floors["rendering"] = (noseg, noseg, tiny)
    if det is not None:
        flops = network_flops(det)
        precision = getattr(det, "precision", "fp32")
        mm = None if precision == "int8" else matmul_gflops(precision=precision)  # no int8 matmul to time
        conv, conv_shape = conv_gflops(det)
        gflops = max(mm or 0.0, conv)
        floors["network"] = flops / (gflops * 1e9) * sum(inputs) / sim_s
    else:
        flops = gflops = precision = mm = conv = conv_shape = None
    if scans:
        cfg = handles["odom_config"]
        per_s = len(scans) / sim_s
        floors["odometry"] = (kiss_core.cpu["odometry"] / sim_s,
                              kiss_floor(scans, cfg.model_copy(update={"deskew": False})) * per_s,
                              kiss_floor(scans, cfg) * per_s)
    return {"sim_s": sim_s, "wall_s": wall, "cpu_s": cpu, "stages": meter.cpu, "calls": meter.calls, "profile": profile,
            "floors": floors, "flops": flops, "gflops": gflops, "matmul_gflops": mm, "conv_gflops": conv,
            "conv_shape": conv_shape, "precision": precision, "images": len(frames), "inputs": sum(inputs), "scans": len(scans),
            "labels": r["labels_summary"]}


def table(m: dict) -> str:
    sim = m["sim_s"]
    fl = m["floors"]
    lines = ["| stage | CPU s / sim s | floor, CPU s / sim s | stage / floor | floor measured as |",
             "|---|---:|---:|---:|---|"]
    how = {"rendering": ("getCameraImage alone, with segmentation (without: {:.3f}" if m.get("profile", "full") == "full"
                         else "getCameraImage alone, without segmentation ({:.3f}")
           + "; {:.3f} of it at any image size: 16x12 pixels cost that)",
           "network": "{flops:.2f} GFLOP per input at {gf:.1f} GFLOP/s, the faster of {prec} matmul ({mm:.1f}) "
                      "and the network's fastest convolution alone ({conv:.1f}: {shape})",
           "network_int8": "{flops:.2f} G operations per input at {gf:.1f} G/s, the network's fastest int8 "
                           "convolution alone ({shape})",
           "odometry": "KISS-ICP's own voxelize, align and map update on the points the stack registers (the "
                       "floor left out); KissICP.register_frame on the same whole sweeps: {:.3f} without its "
                       "deskew, {:.3f} with"}
    for st in STAGES:
        v = m["stages"][st] / sim
        f = fl.get(st)
        if isinstance(f, tuple):
            note, f = how[st].format(*f[1:]), f[0]
        elif f is not None:
            key = "network_int8" if st == "network" and m.get("precision") == "int8" else st
            note = how[key].format(flops=(m["flops"] or 0) / 1e9, gf=m["gflops"] or 0, prec=m.get("precision") or "fp32",
                                  mm=m.get("matmul_gflops") or 0, conv=m.get("conv_gflops") or 0,
                                  shape=m.get("conv_shape") or "-")
        else:
            note = "-"
        fs = "-" if f is None else f"{f:.3f}"
        ratio = "-" if not f else f"{v / f:.1f}x"
        lines.append(f"| {LABELS[st]} | {v:.3f} | {fs} | {ratio} | {note} |")
    lines.append(f"| **all** | **{m['cpu_s'] / sim:.3f}** | | | wall {m['wall_s'] / sim:.2f} s / sim s |")
    return "\n".join(lines)


def plot(m: dict, path, scenario: str | None = None) -> None:
    """The table as a picture (PNG, written atomically): per stage, its CPU seconds per simulated second
    as a bar, its floor as a darker bar inside it, and how far above its floor it runs."""
    from testbed.plots import plt, save

    sim = m["sim_s"]
    rows = []
    for st in STAGES:
        f = m["floors"].get(st)
        rows.append((LABELS[st].split(" (")[0], m["stages"][st] / sim, f[0] if isinstance(f, tuple) else f))
    rows.reverse()  # the table's first row on top
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(rows) + 1.6))
    y = range(len(rows))
    ax.barh(y, [v for _, v, _ in rows], color="tab:blue", alpha=0.45, label="measured")
    ax.barh(y, [f or 0.0 for _, _, f in rows], height=0.4, color="tab:blue", label="floor on this CPU")
    top = max(v for _, v, _ in rows)
    for k, (_, v, f) in enumerate(rows):
        ax.text(v + 0.01 * top, k, f"{v:.3f}" + (f"  ({v / f:.1f}x floor)" if f else "  (no floor)"),
                va="center", fontsize=7)
    ax.set_yticks(list(y))
    ax.set_yticklabels([name for name, _, _ in rows], fontsize=8)
    ax.set_xlim(0, top * 1.45)
    ax.set_xlabel("CPU s per simulated second")
    ax.set_title(f"{scenario or 'default scenario'}, profile {m.get('profile', 'full')}, network "
                 f"{m.get('precision') or 'fp32'}: {m['cpu_s'] / sim:.2f} CPU s per simulated second in all "
                 f"({m['sim_s']:.0f} s simulated)", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    save(fig, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=None, help="bundled name or TOML (default: the default scenario)")
    ap.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's, 60 s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", choices=["full", "fast"], default="full",
                    help="the run profile (fast: camera at half rate, no segmentation image; docs/speed.md)")
    ap.add_argument("--precision", choices=["fp32", "bf16", "int8"], default=None,
                    help="the DOPE network's arithmetic (default: the detector's default; bf16 runs fp32 on a CPU "
                         "without native bfloat16, int8 on one without PyTorch's quantised kernels)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config key, e.g. detector.keyframe_m=0.1 (repeatable)")
    ap.add_argument("--png", type=Path, default=None, metavar="PATH",
                    help="also draw the table as a bar chart, each stage beside its floor (PNG)")
    args = ap.parse_args(argv)
    if args.png is not None and (args.png.is_dir() or not args.png.parent.is_dir()):
        print(f"--png {args.png}: expected a file path in an existing folder", file=sys.stderr)
        return 2
    if args.duration is not None and args.duration <= 0:
        print(f"--duration: expected seconds > 0, got {args.duration}", file=sys.stderr)
        return 2
    from stack.config import ConfigError

    try:
        m = measure(args.scenario, args.duration, args.seed, args.profile, args.precision, tuple(args.set))
    except ConfigError as e:
        print(f"bench_stages: {e}", file=sys.stderr)
        return 2
    ls = m["labels"]
    print(f"profile {args.profile}: {m['sim_s']:.0f} s simulated, {m['images']} images ({m['inputs']} network inputs), {m['scans']} sweeps, network {m['precision']}; {m['cpu_s']:.1f} CPU s, "
          f"{m['wall_s']:.1f} wall s; torch threads {os.environ.get('DOPESLAM_TORCH_THREADS', 'default')}; "
          f"load average {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print(f"map: {ls['labelled']}/{ls['objects']} labelled, {ls['false_labels']} false")
    print(table(m))
    if args.png is not None:
        plot(m, args.png, args.scenario)
        print(f"chart: {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
