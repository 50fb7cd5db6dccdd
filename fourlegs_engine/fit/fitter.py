"""Fit dynamic 3D Gaussians to a calibrated multiview video (the method of Dynamic 3D Gaussians,
Luiten et al., 3DV 2024), resumable per timestep.

Per timestep, in order:

* first timestep: a static 3DGS fit of every parameter (centres, rotations, scales, opacities, colours,
  per-camera colour correction) with densification (clone small / split large Gaussians whose
  screen-space gradient is high, prune transparent and huge ones). Loss: image 0.8·L1 + 0.2·D-SSIM on
  the colour-corrected render (``exp(cam_m)·img + cam_c``) plus the same on the rendered segmentation
  colours (foreground red, background blue) against the masks; optionally (``clean_plate_samples``) an
  L1 term on the background Gaussians rendered alone against each camera's clean plate
  (:mod:`.clean_plate`: the median of its background pixels over timesteps spread across the fitted
  range), whose pixels also seed background points where the people hide it at the first timestep.
* later timesteps: start from a constant-velocity forecast of centres and rotations, move rigid parts of
  the foreground whole at half resolution (:mod:`.clusters`: every part at the first later timestep, which
  has no velocity yet; later only the free ones such as a thrown ball, whose forecast fails when it is
  caught), then optimize only the foreground centres and rotations (colours, opacities, scales, colour
  correction fixed) under the image and segmentation losses plus local rigidity, rotation similarity and
  long-term isometry over the 20 nearest foreground neighbours of the first timestep, and a floor term.
  Background Gaussians are held exactly still (the limit of the paper's heavily weighted background
  term), which makes the background's contribution a fixed image per camera: each view blends the
  foreground alone over that image (exact while the foreground is in front of the background along
  every ray).

Finished timesteps are written to a work directory beside the output (``.NAME.fit/``); a killed fit
resumes from there and produces the identical bundle (every random choice is seeded per timestep).

This module runs the timesteps in order and writes the bundle; the knobs are :mod:`.options`, the model and
its render :mod:`.model`, the per-timestep optimizations :mod:`.optimize`.
"""
from __future__ import annotations

import hashlib
import json
import math
import shutil
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..errors import ConfigMismatchError, InputError, OutputExistsError
from ..fileio import read_json, save_npz_atomic, write_json_atomic
from ..scene.camera import Camera, CameraRig
from ..scene.gaussians import GaussianSequence
from ..scene.scene import Scene
from .clean_plate import clean_plates, sample_timesteps
from .dataset import Capture
from .model import TrainingFrames, average_camera_colours, initial_model, model_from_arrays, to_numpy
from .effort import iterations_for
from .optimize import Tracker, fit_first_timestep, fit_later_timestep, forecast_residual
from .options import FitEvent, FitOptions

WORK_VERSION = 1


# ------------------------------------------------------------------------------------- orchestration
def rig_radius(cameras: list[Camera]) -> float:
    """1.1 × the largest distance of a camera centre from the rig's mean centre: the scale the fit's
    centre learning rates are fractions of."""
    centers = np.stack([c.center for c in cameras])
    return 1.1 * float(np.linalg.norm(centers - centers.mean(0), axis=1).max())


def _work_dir(output: Path) -> Path:
    return output.parent / f".{output.name}.fit"


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    save_npz_atomic(path, **arrays)


_NPZ_KEYS = {"static.npz": ("log_scales", "opacity_logits", "colors", "foreground", "cam_m", "cam_c", "floor_y")}
_STEP_KEYS = ("means", "rotations")


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, MemoryError) as exc:
        raise InputError(f"unreadable checkpoint ({type(exc).__name__}: {exc}); delete it to refit that timestep",
                         file=path) from None
    missing = [k for k in _NPZ_KEYS.get(path.name, _STEP_KEYS) if k not in arrays]
    bad = [k for k, v in arrays.items() if v.dtype.kind == "f" and not np.isfinite(v).all()]
    if missing or bad:
        what = f"lacks {', '.join(missing)}" if missing else f"{', '.join(bad)} hold NaN or Inf"
        raise InputError(f"damaged checkpoint ({what}); delete it to refit that timestep", file=path)
    return arrays


def _generator(seed: int, t: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(int.from_bytes(hashlib.sha256(f"{seed}:{t}".encode()).digest()[:8], "little") & ((1 << 63) - 1))
    return g


def _tqdm_progress(total_timesteps: int):
    from tqdm.auto import tqdm

    bars: dict[str, Any] = {"outer": tqdm(total=total_timesteps, desc="fit", unit="timestep"), "inner": None}

    def callback(ev: FitEvent) -> None:
        if ev.kind == "iteration":
            if bars["inner"] is None:
                bars["inner"] = tqdm(total=ev.total, desc=f"timestep {ev.timestep}", unit="it", leave=False)
            bars["inner"].update(1)
            if ev.index % 10 == 0 or ev.index == ev.total:
                bars["inner"].set_postfix(loss=f"{ev.loss:.4f}", psnr=f"{ev.train_psnr:.2f}")
        elif ev.kind == "timestep":
            if bars["inner"] is not None:
                bars["inner"].close()
                bars["inner"] = None
            bars["outer"].update(1)
            bars["outer"].set_postfix(t=ev.timestep, psnr=f"{ev.train_psnr:.2f}",
                                      **({"resumed": "yes"} if ev.resumed else {}))

    callback.close = lambda: [b.close() for b in bars.values() if b is not None]  # type: ignore[attr-defined]
    return callback


def fit_capture(dataset: str | Path | Capture, output: str | Path, options: FitOptions | None = None, *,
                overwrite: bool = False, progress: bool | Callable[[FitEvent], None] = True,
                check_test_frames: bool = True) -> Path:
    """Fit dynamic Gaussians to a capture and write the native bundle at ``output``.

    Args:
        dataset: directory in the Dynamic 3D Gaussians layout (or an opened :class:`Capture`).
        output: bundle directory to write (refused when it exists unless ``overwrite``).
        options: :class:`FitOptions`.
        overwrite: replace an existing bundle, and restart a partial fit made with other options.
        progress: True for tqdm bars, False for silence, or a callable receiving :class:`FitEvent`.
        check_test_frames: also check the test cameras' frames before fitting (they are read afterwards to
            measure the held-out PSNR).
    Returns:
        the bundle path. Per-Gaussian foreground flags, the per-camera colour correction and per-timestep
        training PSNR are stored in the bundle (``foreground.npy``; ``metadata.fit``). The colours are those
        the average training camera sees (:func:`.model.average_camera_colours`): what a camera the fit
        never saw renders.
    Raises:
        InputError: a malformed dataset (missing frames, bad calibration, mismatched sizes) or options.
        OutputExistsError: ``output`` exists and ``overwrite`` is False.
        ConfigMismatchError: a partial fit with different options exists and ``overwrite`` is False.
    """
    opts = (options or FitOptions()).check()
    output = Path(output)
    if output.exists() and not overwrite:
        raise OutputExistsError(output)
    capture = dataset if isinstance(dataset, Capture) else Capture(dataset)
    steps = capture.timestep_range(opts.timesteps)
    cams_idx = capture.camera_indices("train", opts.cameras)
    capture.check_frames("train", steps, cams_idx, masks=capture.has_masks)
    if check_test_frames:
        capture.check_frames("test", steps, capture.camera_indices("test", None), masks=False)
    device = torch.device("cuda" if opts.device == "cuda" or (opts.device == "auto" and torch.cuda.is_available())
                          else "cpu")
    a = steps.start
    full_cams = [capture.train.cameras[a][c] for c in cams_idx]
    cameras = [c.scaled(opts.resolution_scale) for c in full_cams]
    size = (cameras[0].width, cameras[0].height)
    scene_radius = rig_radius(full_cams)

    work = _work_dir(output)
    config = {"version": WORK_VERSION, "dataset": str(capture.root.resolve()), "options": opts.fingerprint(),
              "timesteps": [steps.start, steps.stop], "cameras": [capture.train.cam_ids[a][c] for c in cams_idx]}
    if work.exists():
        try:
            old = read_json(work / "config.json")
        except InputError as exc:
            if not overwrite:
                raise InputError(f"damaged ({exc.problem}); pass --overwrite / overwrite=True to start the fit again",
                                 file=work / "config.json") from None
            old = None
        if old != json.loads(json.dumps(config)):
            if not overwrite:
                raise ConfigMismatchError(f"{work}: a partial fit with other options or data is there; pass "
                                          "--overwrite / overwrite=True to start again")
            shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    write_json_atomic(work / "config.json", config)

    report = progress if callable(progress) else (_tqdm_progress(len(steps)) if progress else (lambda ev: None))
    try:
        history = _run(capture, steps, cams_idx, cameras, size, opts, device, scene_radius, work, report)
    except BaseException:
        if not (work / "static.npz").is_file():  # nothing finished to resume from: leave nothing behind
            shutil.rmtree(work, ignore_errors=True)
        raise
    finally:
        if hasattr(report, "close"):
            report.close()

    static = _load_npz(work / "static.npz")
    T, N = len(steps), static["colors"].shape[0]
    means = np.empty((T, N, 3), np.float32)
    rotations = np.empty((T, N, 4), np.float32)
    colors = np.empty((T, N, 3), np.float32) if opts.lr_colors_later > 0 else static["colors"]
    for i, t in enumerate(steps):
        z = _load_npz(work / f"t{t:06d}.npz")
        means[i], rotations[i] = z["means"], z["rotations"]
        if colors.ndim == 3:
            colors[i] = z["colors"] if "colors" in z else static["colors"]
    static["colors"], static["cam_m"], static["cam_c"] = average_camera_colours(colors, static["cam_m"],
                                                                                static["cam_c"])
    g = GaussianSequence(means=means, rotations=rotations, log_scales=static["log_scales"],
                         opacity_logits=static["opacity_logits"], colors=static["colors"],
                         foreground=static["foreground"].astype(bool), source=str(capture.root))
    test_idx = capture.camera_indices("test", None)
    rig = CameraRig.static(full_cams, [capture.test.cameras[a][c] for c in test_idx], T)
    metadata = {"source_format": "dynamic3dgs-capture", "source": str(capture.root.resolve()),
                "first_timestep": a,
                "color_correction": {"cam_m": static["cam_m"].tolist(), "cam_c": static["cam_c"].tolist()},
                "fit": {"options": opts.fingerprint(), "train_psnr": history,
                        "later_iterations": _later_iterations(work, steps, opts),
                        "floor_y": float(static["floor_y"][0]) if static["floor_y"].size else None}}
    from ..scene.bundle import write_bundle

    write_bundle(Scene(gaussians=g, cameras=rig, name=capture.root.name, fps=30.0, metadata=metadata), output,
                 overwrite=overwrite)
    shutil.rmtree(work, ignore_errors=True)
    return output


def _later_iterations(work: Path, steps: range, opts: FitOptions) -> dict[str, dict[str, float]]:
    """Per later timestep: its optimization steps and, with the residual-driven schedule, the forecast's
    residual on the moving pixels and their count."""
    effort = _read_effort(work / "effort.json")
    return {str(t): effort.get(str(t), {"iterations": opts.iterations}) for t in steps[1:]}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _read_history(path: Path) -> dict[str, float | None]:
    """``history.json`` of a work folder: timestep -> training PSNR (None: no step taken)."""
    history = read_json(path) if path.is_file() else {}
    if not isinstance(history, dict) or not all(k.isdigit() and (v is None or _is_number(v)) for k, v in history.items()):
        raise InputError("must be a JSON object (timestep -> PSNR); delete it or pass --overwrite", file=path)
    return history


def _read_effort(path: Path) -> dict[str, dict[str, float]]:
    """``effort.json`` of a work folder: timestep -> {residual, moving_pixels, iterations} of its schedule."""
    effort = read_json(path) if path.is_file() else {}
    if not isinstance(effort, dict) or not all(
            k.isdigit() and isinstance(e, dict) and all(_is_number(e.get(f)) for f in ("residual", "iterations"))
            for k, e in effort.items()):
        raise InputError("must be a JSON object (timestep -> residual, moving pixels, iterations); delete it or "
                         "pass --overwrite", file=path)
    return effort


def _run(capture: Capture, steps: range, cams_idx: list[int], cameras: list[Camera], size: tuple[int, int],
         opts: FitOptions, device, scene_radius: float, work: Path, report) -> list[float]:
    """Fit (or resume) every timestep of ``steps`` into ``work``; returns training PSNR per timestep."""
    a = steps.start
    history_path = work / "history.json"
    history = _read_history(history_path)
    static_path = work / "static.npz"
    if static_path.is_file() and (work / f"t{a:06d}.npz").is_file():
        s = _load_npz(static_path)
        z = _load_npz(work / f"t{a:06d}.npz")
        model = model_from_arrays(z["means"], z["rotations"], s, device)
        floor_y = float(s["floor_y"][0]) if s["floor_y"].size else None
        report(FitEvent("timestep", a, train_psnr=history.get(str(a), float("nan")), resumed=True))
    else:
        frames = TrainingFrames(capture, a, cams_idx, size, device)
        if capture.has_masks and opts.clean_plate_samples > 0:
            frames.add_clean_plates(clean_plates(capture, cams_idx, sample_timesteps(steps, opts.clean_plate_samples),
                                                 size), device)
        model, floor_y = initial_model(frames, cameras, opts, device)
        model, last = fit_first_timestep(model, frames, cameras, opts, scene_radius, _generator(opts.seed, a), report, a)
        _save_npz(static_path, log_scales=to_numpy(model.log_scales), opacity_logits=to_numpy(model.opacity_logits),
                  colors=to_numpy(model.colors), foreground=to_numpy(model.foreground), cam_m=to_numpy(model.cam_m),
                  cam_c=to_numpy(model.cam_c), floor_y=np.asarray([] if floor_y is None else [floor_y], np.float64))
        # the model continues from its float32 round trip, exactly as a resumed run would
        s = _load_npz(static_path)
        _save_npz(work / f"t{a:06d}.npz", means=to_numpy(model.means), rotations=to_numpy(model.rotations))
        z = _load_npz(work / f"t{a:06d}.npz")
        model = model_from_arrays(z["means"], z["rotations"], s, device)
        history[str(a)] = last
        write_json_atomic(history_path, history)
        report(FitEvent("timestep", a, train_psnr=last))
    if len(steps) == 1:
        return [history[str(a)]]
    tracker = Tracker(model, cameras, opts, floor_y)
    prev2 = prev = (model.means, model.rotations)
    colors = model.colors  # (N,3) the previous timestep's (they change only with lr_colors_later)
    effort_path = work / "effort.json"
    effort = _read_effort(effort_path)
    previous_frames: TrainingFrames | None = None
    for t in steps[1:]:
        path = work / f"t{t:06d}.npz"
        if path.is_file():
            z = _load_npz(path)
            cur = (torch.from_numpy(z["means"]).to(device), torch.from_numpy(z["rotations"]).to(device))
            if "colors" in z:
                colors = torch.from_numpy(z["colors"]).to(device)
            report(FitEvent("timestep", t, train_psnr=history.get(str(t), float("nan")), resumed=True))
            previous_frames = None
        else:
            frames = TrainingFrames(capture, t, cams_idx, size, device)
            if opts.max_iterations > 0:
                previous_frames = previous_frames or TrainingFrames(capture, t - 1, cams_idx, size, device)
                residual, moved = forecast_residual(model, tracker, frames, previous_frames, cameras, prev, prev2,
                                                    colors)
                earlier = [e["residual"] for k, e in effort.items() if int(k) < t]
                n_iter = iterations_for(residual, earlier, opts.iterations, min(opts.min_iterations, opts.iterations),
                                        opts.max_iterations)
                effort[str(t)] = {"residual": residual, "moving_pixels": moved, "iterations": n_iter}
                write_json_atomic(effort_path, effort)
            else:
                n_iter = opts.iterations
            m, r, colors, last = fit_later_timestep(model, tracker, frames, cameras, opts, scene_radius, prev, prev2,
                                                    _generator(opts.seed, t), report, t, n_iter, colors)
            previous_frames = frames
            per_timestep = {"colors": to_numpy(colors)} if opts.lr_colors_later > 0 else {}
            _save_npz(path, means=to_numpy(m), rotations=to_numpy(r), **per_timestep)
            z = _load_npz(path)
            cur = (torch.from_numpy(z["means"]).to(device), torch.from_numpy(z["rotations"]).to(device))
            if "colors" in z:
                colors = torch.from_numpy(z["colors"]).to(device)
            history[str(t)] = last if math.isfinite(last) else None  # no step taken (iterations=0)
            write_json_atomic(history_path, history)
            report(FitEvent("timestep", t, train_psnr=last))
        prev2, prev = prev, cur
    return [history.get(str(t), float("nan")) for t in steps]
