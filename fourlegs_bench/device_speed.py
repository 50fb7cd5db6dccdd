"""The speed steps of ``fourlegs bench device`` (:mod:`.device_steps`): ViCLIP and the rasterizer."""
from __future__ import annotations

import statistics
import time

from .device_steps import CPU_FIGURES, REPO, StepContext, StepSkipped, cpu_figures, gsplat_usable, one_line, \
    require_cuda, sync


def step_viclip(ctx: StepContext) -> None:
    """ViCLIP at the plan's size, random weights: seconds per clip per (precision, batch size), the worst
    cosine of each precision to float32 on real crop clips, seconds per camera-timestep (the device's own
    decoding and crop pre-processing plus clips x seconds per clip) and the whole-scene hours."""
    import torch

    from fourlegs_engine.language.extract import ExtractOptions
    from fourlegs_engine.language.pyramid import crop_layout, pyramid_ratios
    from fourlegs_engine.language.viclip.model import ViCLIPConfig, ViCLIPModel, l2_normalize, video_clip_flops

    from .viclip import DTYPES, _cast
    from .viclip_real import PAPER_CLIPS_640x360, load_tube, preprocess_camera_timestep, sample_clips

    plan, device = ctx.plan, ctx.device
    config = ViCLIPConfig.preset(plan["size"]) if isinstance(plan["size"], str) else ViCLIPConfig(**plan["size"])
    crop = int(ExtractOptions(crop_size=None).resolved_crop_size("rgb", config))
    reference_clips = int(plan["reference_clips"])
    ctx.record(model=config.size_name, device=str(device), flops_per_clip=video_clip_flops(config)["total"],
               weights="random (seeded): seconds depend only on shapes")

    # real clips and the device's own pre-processing of one camera-timestep
    if ctx.data is not None:
        from fourlegs_engine.fit.dataset import Capture
        capture = Capture(ctx.data)
        cam = capture.camera_indices("train", [str(plan["camera"])])[0]
        t = min(int(plan["timestep"]), capture.num_timesteps - 1)
        layout = crop_layout(capture.width, capture.height, pyramid_ratios())
        keep = [i for _, i in sample_clips(layout, 1, reference_clips)]
        tube, decoded = load_tube(capture, t, cam)
        decode_s = decoded["seconds"] / decoded["frames"]
        start = time.perf_counter()
        kept, produced = preprocess_camera_timestep(tube, layout, crop, keep)
        prep_s = time.perf_counter() - start
        real = torch.stack([kept[i] for i in keep])
        ctx.record(clips_source=f"{ctx.data} camera {plan['camera']} timestep {t}", image_size=[capture.width,
                   capture.height], clips_per_camera_timestep=produced,
                   paper_clips_per_camera_timestep=PAPER_CLIPS_640x360,
                   decode_seconds_per_frame=decode_s, crop_resize_seconds_per_camera_timestep=prep_s)
    else:
        gen = torch.Generator().manual_seed(0)
        real = torch.randn(reference_clips, config.num_frames, 3, crop, crop, generator=gen)
        produced, decode_s, prep_s = PAPER_CLIPS_640x360, None, None
        ctx.record(clips_source="random normal clips (no capture data)", clips_per_camera_timestep=produced,
                   decode_seconds_per_frame=None, crop_resize_seconds_per_camera_timestep=None)

    torch.manual_seed(int(plan.get("seed", 0)))
    with torch.device(device):
        master = ViCLIPModel(config).eval()
    with torch.inference_mode():
        reference = l2_normalize(master.encode_video(real.to(device, torch.float32)).double().cpu())
    subsets = plan["subsets"]
    for dtype_name in plan["dtypes"]:
        dtype = DTYPES[dtype_name]
        try:
            model = master if dtype == torch.float32 else _cast(master, dtype)
            with torch.inference_mode():
                emb = l2_normalize(model.encode_video(real.to(device, dtype)).double().cpu())
        except (RuntimeError, NotImplementedError) as exc:
            ctx.append("rows", {"dtype": dtype_name, "supported": False, "error": one_line(exc)})
            continue
        cosine = float((emb * reference).sum(-1).min())
        for batch in plan["batches"][dtype_name]:
            if ctx.remaining() < 5:
                ctx.append("rows", {"dtype": dtype_name, "batch_size": batch, "supported": True,
                                    "skipped": "out of the step's time"})
                continue
            clips = real[torch.arange(batch) % real.shape[0]].to(device, dtype)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            times = []
            with torch.inference_mode():
                for k in range(1 + int(plan["repeats"])):      # the first call (kernel selection) is not timed
                    sync(device)
                    start = time.perf_counter()
                    out = model.encode_video(clips)
                    sync(device)
                    if k:
                        times.append(time.perf_counter() - start)
            per_clip = statistics.median(times) / batch
            row = {"dtype": dtype_name, "batch_size": batch, "supported": True, "seconds_per_clip": per_clip,
                   "clips_per_second": 1.0 / per_clip,
                   "tflop_per_second": ctx.result["flops_per_clip"] / per_clip / 1e12,
                   "min_cosine_to_float32": cosine, "finite": bool(torch.isfinite(out).all()),
                   "peak_gib": (torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None),
                   "network_seconds_per_camera_timestep": produced * per_clip}
            if prep_s is not None:
                row["seconds_per_camera_timestep"] = decode_s + prep_s + produced * per_clip
            per_ct = row.get("seconds_per_camera_timestep", row["network_seconds_per_camera_timestep"])
            row["extrapolated_hours"] = {name: cams * steps * per_ct / 3600 for name, (cams, steps) in subsets.items()}
            ctx.append("rows", row)
            del clips, out
        del model
    cpu = cpu_figures("viclip")
    if cpu:
        ctx.record(cpu_rows=[{k: r.get(k) for k in ("dtype", "batch_size", "seconds_per_clip",
                                                    "seconds_per_camera_timestep", "extrapolated_hours")}
                             for r in cpu["rows"] if r.get("supported") and r["dtype"] in ("float32", "bfloat16")],
                   cpu_source=str(CPU_FIGURES["viclip"].relative_to(REPO)))


# ----------------------------------------------------------------------------------------- raster
#: the figure issue #34 cites for gsplat at 1920x1080
GSPLAT_PUBLISHED_FPS_1080P = 160.0


def _raster_step(ctx: StepContext, backend: str) -> None:
    """The rasterizer at the plan's N: RGB and C-channel features, forward and forward+backward, per
    resolution; median ms per frame and frames per second."""
    import torch

    from .render import _render_fn
    from .render_scene import make_bench_scene

    plan, device = ctx.plan, ctx.device
    if backend == "gsplat":
        require_cuda(ctx)
        if not gsplat_usable():
            raise StepSkipped("gsplat is not usable (see the gsplat build); the torch backend's rows stand alone")
    ctx.record(backend=backend, device=str(device), n=plan["n"], channels=plan["channels"],
               gsplat_published_fps_1080p=GSPLAT_PUBLISHED_FPS_1080P)
    for width, height in plan["resolutions"]:
        scene = make_bench_scene(plan["n"], feature_dim=plan["channels"], seed=0, device=device, width=width,
                                 height=height)
        for output in plan["outputs"]:
            for mode in plan["modes"]:
                if ctx.remaining() < 3:
                    ctx.append("rows", {"width": width, "height": height, "output": output, "mode": mode,
                                        "skipped": "out of the step's time"})
                    continue
                fn = _render_fn(scene, output, mode, backend)
                if device.type == "cuda":
                    torch.cuda.reset_peak_memory_stats(device)
                sync(device)
                start = time.perf_counter()
                fn()                                      # warm-up: allocation, kernel selection
                sync(device)
                warm = time.perf_counter() - start
                # slow cases get fewer timed runs so one slow configuration cannot eat the step
                repeats = int(plan["repeats"]) if warm < 1.0 else (1 if warm < 5.0 else 0)
                times = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    fn()
                    sync(device)
                    times.append(time.perf_counter() - start)
                ms = 1000 * (statistics.median(times) if times else warm)
                ctx.append("rows", {"width": width, "height": height, "output": output, "mode": mode,
                                    "ms_median": ms, "fps": 1000.0 / ms, "timed_runs": len(times),
                                    "warmup_ms": 1000 * warm,
                                    "peak_mb": (torch.cuda.max_memory_allocated(device) / 2**20
                                                if device.type == "cuda" else None)})
        del scene
    cpu = cpu_figures("render")
    if cpu:
        ctx.record(cpu_rows=[{k: r.get(k) for k in ("n", "output", "mode", "ms_median", "width", "height")}
                             for r in cpu if r.get("part") == "speed" and r.get("n") == 300_000
                             and r.get("kernel", "v2") == "v2"],
                   cpu_source=str(CPU_FIGURES["render"].relative_to(REPO)))


def step_raster_torch(ctx: StepContext) -> None:
    _raster_step(ctx, "torch")


def step_raster_gsplat(ctx: StepContext) -> None:
    _raster_step(ctx, "gsplat")
