"""Shots framed on the action region (:mod:`.framing`): the zoom that ends where the region fills the
frame and the orbit about it, both keeping clear of the scene's other Gaussians."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .camera_paths import Pose, interpolate_poses, look_at_rotation, slerp_rotations
from .shot_context import ShotContext, ShotPath


def _cylindrical(point: np.ndarray, centre: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """(ex, ey) horizontal basis about ``up``, and the angle, horizontal radius and height of ``point``."""
    ez = up / np.linalg.norm(up)
    ex = np.eye(3)[int(np.argmin(np.abs(ez)))]
    ex = ex - (ex @ ez) * ez
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    r = np.asarray(point, dtype=np.float64) - centre
    return ex, ey, math.atan2(r @ ey, r @ ex), math.hypot(r @ ex, r @ ey), float(r @ ez)


def _spherical_frame(point: np.ndarray, centre: np.ndarray, up: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """Basis (ex, ey, ez = up) about ``centre`` and ``point``'s azimuth, elevation (radians) and distance."""
    ex, ey, azimuth, horizontal, height = _cylindrical(point, centre, up)
    return ex, ey, np.cross(ex, ey), azimuth, math.atan2(height, horizontal), max(math.hypot(horizontal, height), 1e-9)


def _spherical_points(centre, ex, ey, ez, azimuth, elevation, distance) -> np.ndarray:
    """(n,3) points at (n,) azimuth/elevation (radians) and distance from ``centre``."""
    az, el, d = (np.broadcast_to(np.asarray(v, dtype=np.float64), np.shape(azimuth)) for v in (azimuth, elevation, distance))
    horiz = d * np.cos(el)
    return (centre[None] + (horiz * np.cos(az))[:, None] * ex + (horiz * np.sin(az))[:, None] * ey
            + (d * np.sin(el))[:, None] * ez)


def upright(eye: np.ndarray, centre: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The rotation looking from ``eye`` at ``centre``, level about ``up``."""
    return look_at_rotation(eye, centre, up)


MAX_ELEVATION = math.radians(75.0)
#: Seconds a shot that follows the subject takes to turn from the previous shot's view onto it.
FOLLOW_TURN_S = 0.5


def _is_level(rotation: np.ndarray, up: np.ndarray, tol: float = 1e-6) -> bool:
    """The camera has no roll: its image x axis is horizontal (perpendicular to ``up``)."""
    return abs(float(np.asarray(rotation)[:, 0] @ (up / np.linalg.norm(up)))) < tol


def level_blend(R0: np.ndarray, R1: np.ndarray, weight: float, up: np.ndarray) -> np.ndarray:
    """(3,3) the rotation ``weight`` of the way from ``R0`` to ``R1`` (slerp); when both are level (no roll
    about ``up``) the result is levelled too, keeping its view direction."""
    R = slerp_rotations(R0, R1, [weight])[0]
    if weight in (0.0, 1.0) or not (_is_level(R0, up) and _is_level(R1, up)):
        return R
    return look_at_rotation(np.zeros(3), R[:, 2], up, previous=R)


def target_distance(framing, focal_px: float, resolution, target_height: float) -> float:
    """Distance (metres) at which the framed subject's height spans ``target_height`` of the frame height
    through a lens of ``focal_px`` (pinhole: height_px = focal * height_m / distance)."""
    return float(focal_px) * framing.region.height / (float(target_height) * float(resolution[1]))


def framed_zoom(p: dict[str, Any], ctx: ShotContext, times: np.ndarray, facts: dict[str, Any], start: Pose,
                f0: float, e: np.ndarray) -> ShotPath:
    """Zoom onto the action region: end where its sphere fills the frame (never nearer than the preset's
    magnification allows), with a clear line of sight and every Gaussian beyond the near plane on
    every frame. The end direction is the start's unless that path is blocked; then the nearest
    direction around the action (other azimuth, higher elevation) whose path is clear, else a shorter
    zoom. The camera ends level (upright about the scene's up) and aimed at the region's centre."""
    fr = ctx.framing
    c, up = fr.centre, ctx.up
    ex, ey, ez, az0, el0, d0 = _spherical_frame(start.position, c, up)
    if p["mode"] == "focal":
        return _framed_focal_zoom(p, ctx, times, facts, start, f0, e)
    closest = fr.region.radius + fr.near + p["min_distance_m"]
    if p.get("target_height", 0.0) > 0:
        d_target = target_distance(fr, f0, ctx.resolution, p["target_height"])
        d_end = min(d0, max(d_target, closest))
    else:
        d_fit = fr.framing_distance(f0, ctx.resolution, fill=0.9)
        d_end = min(d0, max(d_fit, d0 / p["factor"], closest))
    candidates = []
    for d_scale in (1.0, 1.15, 1.3, 1.5):
        d1 = min(d0, d_end * d_scale)
        for del_deg in (0, 10, 20, 30, 45):
            el1 = min(el0 + math.radians(del_deg), MAX_ELEVATION) if del_deg else el0
            for daz_deg in (0, 20, -20, 40, -40, 60, -60, 90, -90):
                cost = abs(daz_deg) / 90 + del_deg / 45 + (d_scale - 1.0) * 2
                candidates.append((cost, d1, el1, math.radians(daz_deg)))
    candidates.sort(key=lambda c_: c_[0])
    best, best_bad, chosen = None, math.inf, None
    for cost, d1, el1, daz in candidates:
        az = az0 + daz * e
        el = el0 + (el1 - el0) * e
        dist = d0 * (d1 / d0) ** e
        eyes = _spherical_points(c, ex, ey, ez, az, el, dist)
        eyes[0] = start.position if e[0] == 0 else eyes[0]
        coarse = np.unique(np.linspace(0, len(e) - 1, min(len(e), 9)).round().astype(int))
        if best is not None and fr.path_badness(eyes[coarse]) > 0:
            continue
        bad = fr.path_badness(eyes)
        if bad < best_bad:
            best, best_bad, chosen = eyes, bad, (d1, el1, daz)
        if bad == 0.0:
            break
    eyes = best
    end_rot = upright(eyes[-1], c, up)
    rots = slerp_rotations(start.rotation, end_rot, e)
    if _is_level(start.rotation, up):   # a level start stays level all the way (slerp alone would roll a little)
        rots = [look_at_rotation(q, q + R[:, 2], up, previous=R) for q, R in zip(eyes, rots)]
    poses = follow_subject([Pose(q, R) for q, R in zip(eyes, rots)], times, ctx, FOLLOW_TURN_S)
    d1, el1, daz = chosen
    if best_bad > 0:
        ctx.messages.append("zoom_in: no approach keeps a clear view of the action on every frame; the least "
                            "obstructed one is used")
    elif d1 > d_end + 1e-9:
        ctx.messages.append(f"zoom_in: shortened to end {d1:.2f} m from the action (a closer end is obstructed)")
    focals = np.full(len(poses), f0)
    d_last = float(np.linalg.norm(eyes[-1] - c))
    if p.get("target_height", 0.0) > 0:
        # the lens makes up what the approach could not: the subject ends at the target size
        f_end = max(f0, f0 * d_last / max(target_distance(fr, f0, ctx.resolution, p["target_height"]), 1e-9))
        focals = f0 * (f_end / f0) ** e
    return ShotPath(poses, focals, times, {
        **p, **facts, "distance_start": d0, "distance_end": d_last, "subject_height_m": fr.region.height,
        "framed_centre": [float(v) for v in c], "region_radius": fr.region.radius,
        "end_turn_deg": math.degrees(daz), "end_elevation_deg": math.degrees(el1), "clear": best_bad == 0.0})


def _framed_focal_zoom(p, ctx, times, facts, start, f0, e) -> ShotPath:
    """Focal-length zoom: magnify up to ``factor`` but no further than the region filling the frame."""
    fr = ctx.framing
    c = fr.centre
    d0 = float(np.linalg.norm(start.position - c))
    half = math.atan(0.5 * min(ctx.resolution) / f0)
    fit_half = math.asin(min(0.999, fr.region.radius / max(d0, 1e-9)) / 0.9) if fr.region.radius < d0 * 0.9 else half
    magnification_fit = max(1.0, math.tan(half) / math.tan(max(fit_half, 1e-6)))
    if p.get("target_height", 0.0) > 0:
        magnification_fit = max(1.0, d0 / target_distance(fr, f0, ctx.resolution, p["target_height"]))
        mag = magnification_fit ** e
    else:
        mag = min(p["factor"], magnification_fit) ** e
    end = Pose(start.position, upright(start.position, c, ctx.up))
    poses = interpolate_poses(start, end, np.clip(e * 4.0, 0.0, 1.0))
    return ShotPath(poses, f0 * mag, times, {**p, **facts, "distance_start": d0, "distance_end": d0,
                                             "framed_centre": [float(v) for v in c],
                                             "region_radius": fr.region.radius})


def framed_orbit(p: dict[str, Any], ctx: ShotContext, times: np.ndarray, facts: dict[str, Any], start: Pose,
                 f0: float, e: np.ndarray) -> ShotPath:
    """Bullet-time orbit about the up axis through the action region's centre, at a distance that frames
    the region, with a clear view and every Gaussian beyond the near plane on every frame.

    Tries the preset's arc at the start's distance and elevation first, then higher elevations, longer
    distances and the opposite direction; the move to the chosen distance/elevation happens over the
    first sixth of the arc. When no orbit is clear, the preset's (or the least obstructed of those checked
    on every frame) is used, with a message.
    """
    fr = ctx.framing
    c, up = fr.centre, ctx.up
    ex, ey, ez, az0, el0, d0 = _spherical_frame(start.position, c, up)
    arc = math.radians(p["arc_deg"])
    ramp = np.clip(e / (1.0 / 6.0), 0.0, 1.0)
    ramp = ramp * ramp * (3.0 - 2.0 * ramp)
    fits = []   # (lens scale, orbit distance, extra cost)
    for lens in (1.0, 0.8, 0.65, 0.5, 0.4):   # a wider lens frames the region from closer in
        if p.get("target_height", 0.0) > 0:   # the subject at its target size through the (wider) lens
            fits.append((lens, max(target_distance(fr, f0 * lens, ctx.resolution, p["target_height"]),
                                   fr.region.radius + 2 * fr.near), 0.0))
        # never a closer framing than the shot it continues (the zoom's end sets the magnification); with a
        # target size, the fallback where no orbit at that size stays clear and inside the rig
        fits.append((lens, max(fr.framing_distance(f0 * lens, ctx.resolution, fill=0.9),
                               fr.region.radius + 2 * fr.near, d0 * lens),
                     3.0 if p.get("target_height", 0.0) > 0 else 0.0))
    candidates = []
    for lens, d_fit, extra in fits:
        for sign in (1.0, -1.0):
            for d_scale in (1.0, 1.15):
                for del_deg in (0, 15, 30, 45, 60):
                    el1 = float(min(el0 + math.radians(del_deg), MAX_ELEVATION))
                    d1 = d_fit * d_scale * p["radius_scale"]
                    cost = extra + (1.0 - lens) * 4 + (sign < 0) * 1.5 + (d_scale - 1.0) * 3 + abs(del_deg) / 30
                    candidates.append((cost, sign, d1, el1, lens))
    candidates.sort(key=lambda c_: c_[0])
    best, best_bad, chosen = None, math.inf, None
    coarse = np.unique(np.linspace(0, len(e) - 1, min(len(e), 13)).round().astype(int))
    for cost, sign, d1, el1, lens in candidates:
        az = az0 + sign * arc * e
        el = el0 + (el1 - el0) * ramp
        dist = d0 + (d1 - d0) * ramp
        eyes = _spherical_points(c, ex, ey, ez, az, el, dist)
        if fr.path_badness(eyes[coarse]) > 0:   # cheap look at a few frames first
            if best is None:
                best, best_bad, chosen = eyes, fr.path_badness(eyes), (sign, d1, el1, lens)
            continue
        bad = fr.path_badness(eyes)
        if bad < best_bad:
            best, best_bad, chosen = eyes, bad, (sign, d1, el1, lens)
        if bad == 0.0:
            break
    eyes = best
    sign, d1, el1, lens = chosen
    focals = f0 * lens ** ramp
    level = [upright(q, c, up) for q in eyes]
    # a start that is not level (e.g. a best view turned by the smallest rotation) is carried along
    # rigidly and levelled over the ramp
    offset = level[0].T @ start.rotation
    if _is_level(start.rotation, up):
        offset = np.eye(3)
    poses = [Pose(q, slerp_rotations(R @ offset, R, [w])[0]) for q, R, w in zip(eyes, level, ramp)]
    poses[0] = start
    if best_bad > 0:
        ctx.messages.append("bullet_time: no orbit keeps a clear view of the action on every frame; the "
                            "preset's orbit (or the least obstructed one checked in full) is used")
    return ShotPath(poses, focals, times, {
        **p, **facts, "centre": [float(v) for v in c], "region_radius": fr.region.radius, "lens_scale": lens,
        "rigid": False,
        "radius": float(d1 * math.cos(el1)), "height": float(d1 * math.sin(el1)),
        "arc_deg_used": math.degrees(sign * arc), "elevation_deg": math.degrees(el1), "clear": best_bad == 0.0})



def follow_subject(poses: list[Pose], times: np.ndarray, ctx: ShotContext, transition_s: float) -> list[Pose]:
    """The same camera positions turned (level about the scene's up) onto the framed subject's centre at
    each frame's scene time (:attr:`Framing.track`), so a replay follows the subject instead of the spot
    where it was at the peak. A shot that continues the previous one starts from its last pose and turns
    onto the subject over ``transition_s`` (at most :data:`FOLLOW_TURN_S`); one that cut to its camera
    follows from its first frame. Unchanged without a framed subject's track."""
    fr = ctx.framing
    if fr is None or fr.track is None or not poses:
        return poses
    targets = fr.track_at(times)
    n = len(poses)
    # a shot that cut to its camera (its first pose is not the previous one's) follows from its first frame
    continuing = ctx.previous is not None and bool(
        np.allclose(poses[0].position, ctx.previous.position) and np.allclose(poses[0].rotation, ctx.previous.rotation))
    if not continuing:
        w = np.ones(n)
    else:
        m = min(n, max(2, int(round(min(transition_s, FOLLOW_TURN_S) * ctx.output_fps))))
        ramp = np.clip(np.arange(n) / max(m - 1, 1), 0.0, 1.0)
        w = ramp * ramp * (3.0 - 2.0 * ramp)
    out = []
    for pose, target, wi in zip(poses, targets, w):
        level = upright(pose.position, target, ctx.up)
        out.append(Pose(pose.position, level_blend(pose.rotation, level, float(wi), ctx.up)))
    if continuing:
        out[0] = poses[0]
    return out
