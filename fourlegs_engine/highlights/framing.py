"""Framing the action: the relevant region's extent, the scene's up direction, and line-of-sight tests.

Pure geometry on the scene's Gaussians at one timestep (the peak), used by the shot builders so that
close-ups frame the action instead of whatever stands near the best camera:

- :func:`scene_up` — the world direction that is up for the capture (cameras of a real rig are held
  upright; synthetic scenes use +z), so orbits turn about the vertical and replays stay level.
- :func:`action_region` — centre and radius of the relevant Gaussians (relevancy above the paper's
  0.5), from robust percentiles so a few stray relevant Gaussians do not inflate the shot.
- :class:`Framing` — the region plus the scene's Gaussians as obstacles: :meth:`Framing.occlusion`
  is how much of the view of the action centre the non-action Gaussians hide from a camera position
  (each Gaussian hides ``opacity * exp(-m²/2)`` where the segment camera→centre passes at Mahalanobis
  distance ``m <= 3`` from it), :meth:`Framing.clearance` is how far a camera is from the nearest
  Gaussian's 3-sigma ellipsoid surface (a camera closer than the renderer's near plane to a Gaussian
  would cut that splat off, see :data:`NEAR_CLIP_M`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .instances import split_instances
from .rig_volume import RigVolume

#: Relevancy above which a Gaussian belongs to the action (the paper's threshold).
RELEVANT = 0.5
#: Near clipping distance of the highlight camera (Blender's default camera clip_start, metres): the
#: renderer drops every Gaussian whose centre is nearer than this, so framed cameras keep every
#: Gaussian's 3-sigma ellipsoid at least this far away.
NEAR_CLIP_M = 0.1
#: Gaussians fainter than this neither hide the action nor count for the near-plane clearance.
MIN_OPACITY = 0.1
#: A camera position "sees" the action when the Gaussians between it and the action centre hide at
#: most this fraction of it.
MAX_OCCLUSION = 0.25
#: Half-width over depth of the view cone within which a Gaussian near the camera counts for the
#: near-plane clearance (a half field of view of about 56 degrees, wider than the diagonal of the
#: presets' lenses).
NEAR_CONE_SLOPE = 1.5
#: Mahalanobis radius of a Gaussian's extent (3 sigma).
SIGMAS = 3.0
#: a lens is widened to fit a subject at most to this share of its focal length (a wider lens shows what
#: the capture's cameras never saw)
MAX_PULL_BACK = 0.5

_CANONICAL_AXES = np.eye(3)


def scene_up(cameras: Sequence, *, snap_deg: float = 15.0) -> np.ndarray:
    """(3,) unit up direction of a capture, from its cameras.

    Cameras of a rig are held without roll, so each camera's image x axis (its "right") is horizontal
    whatever its pitch — even for a camera looking straight down: up is the direction most nearly
    perpendicular to all of them (the least eigenvector of their scatter), signed to agree with the
    cameras' mean image-up (-y). When the right vectors do not pin it down (all cameras facing one
    way), the mean image-up made perpendicular to the common right vector is used. A result within
    ``snap_deg`` of a signed world axis is snapped onto it. Without cameras, +z.
    """
    c2ws = [np.asarray(c.c2w, dtype=np.float64) for c in cameras]
    if not c2ws:
        return np.array([0.0, 0.0, 1.0])
    rights = np.stack([m[:3, 0] for m in c2ws])
    mean_up = -np.mean([m[:3, 1] for m in c2ws], axis=0)
    vals, vecs = np.linalg.eigh(rights.T @ rights / len(rights))
    if vals[1] - vals[0] > 0.05:
        up = vecs[:, 0]
    else:
        up = mean_up - (mean_up @ vecs[:, 2]) * vecs[:, 2]
    n = float(np.linalg.norm(up))
    if not n > 1e-6 or not np.isfinite(n):
        return np.array([0.0, 0.0, 1.0])
    up = up / n
    if up @ mean_up < 0:
        up = -up
    axes = np.concatenate([_CANONICAL_AXES, -_CANONICAL_AXES])
    best = axes[int(np.argmax(axes @ up))]
    if float(best @ up) >= math.cos(math.radians(snap_deg)):
        return best.copy()
    return up


@dataclass(frozen=True)
class ActionRegion:
    """Where the framed subject is at one timestep.

    Attributes:
        centre: (3,) the middle of the subject's Gaussians (per-axis percentile box).
        radius: distance from ``centre`` within which the robust share of them lies, plus their 3-sigma
            size (metres).
        members: (N,) bool, the subject's Gaussians.
        height: the subject's extent along the scene's up (metres).
        instances: every instance the query matches, best first (:mod:`.instances`); the subject is
            ``instances[index]``.
        index: which instance is framed.
    """

    centre: np.ndarray
    radius: float
    members: np.ndarray
    height: float = 0.0
    instances: tuple = ()
    index: int = 0


def action_region(means: np.ndarray, relevancy: np.ndarray, scales: np.ndarray, opacities: np.ndarray, *,
                  threshold: float = RELEVANT, min_members: int = 8, min_share: float = 0.01,
                  up: Optional[np.ndarray] = None, foreground: Optional[np.ndarray] = None,
                  instance: int = 0) -> Optional[ActionRegion]:
    """The region of one instance of the relevant Gaussians, or None when fewer than ``min_members`` are
    relevant (or there is no instance number ``instance``).

    A lifted field marks a few scattered Gaussians of the background relevant too, and a query may
    match several separate things: the relevant Gaussians are split into instances (3D connected
    components, :func:`.instances.split_instances`, best first) and the region is instance number
    ``instance`` (0: the one with the largest relevancy mass).

    Args:
        means: (N,3) Gaussian centres at the timestep.
        relevancy: (N,) per-Gaussian relevancy in [0,1].
        scales: (N,3) standard deviations along the Gaussians' axes.
        opacities: (N,) in [0,1]; Gaussians fainter than :data:`MIN_OPACITY` are not part of the region.
        threshold: relevancy above which a Gaussian is relevant.
        up: (3,) the scene's up (default +z); foreground: (N,) bool or None.
    """
    means = np.asarray(means, dtype=np.float64)
    rel = np.nan_to_num(np.asarray(relevancy, dtype=np.float64), nan=0.0)
    ok = np.isfinite(means).all(axis=1)
    members = (rel > threshold) & (np.asarray(opacities) >= MIN_OPACITY) & ok
    if int(members.sum()) < min_members:
        return None
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    found = split_instances(means, rel, scales, members, up, foreground=foreground, min_members=min_members,
                            min_share=min_share)
    if not 0 <= instance < len(found):
        return None
    subject = found[instance]
    return ActionRegion(centre=subject.centre, radius=subject.radius, members=subject.members,
                        height=subject.height, instances=tuple(found), index=int(instance))


def _segment_mahalanobis(eyes: np.ndarray, target: np.ndarray, means: np.ndarray, whiten: np.ndarray) -> np.ndarray:
    """(K,M) smallest Mahalanobis distance from each segment eye→target to each Gaussian.

    eyes (K,3), target (3,), means (M,3), whiten (M,3,3) maps a world offset to sigma units.
    """
    a = np.einsum("mij,kmj->kmi", whiten, eyes[:, None, :] - means[None])        # (K,M,3)
    b = np.einsum("mij,mj->mi", whiten, target[None] - means)[None]              # (1,M,3)
    d = b - a
    dd = np.maximum((d * d).sum(-1), 1e-300)
    s = np.clip(-(a * d).sum(-1) / dd, 0.0, 1.0)
    closest = a + s[..., None] * d
    return np.sqrt((closest * closest).sum(-1))


@dataclass
class Framing:
    """The action region and the scene's Gaussians at the peak, for line-of-sight tests (see module doc).

    Attributes:
        up: (3,) the scene's up direction.
        region: the action region.
        means, whiten, opacities, reach: the obstacles (Gaussians outside the region's sphere that are
            not relevant, opacity >= :data:`MIN_OPACITY`): (M,3) centres, (M,3,3) world→sigma-unit maps,
            (M,) opacities, (M,) 3-sigma radii (largest axis).
        solid_means, solid_reach: every Gaussian with opacity >= :data:`MIN_OPACITY` (relevant or not):
            (S,3) centres and (S,) 3-sigma radii, for the near-plane clearance.
        near: the camera's near clipping distance (metres).
    """

    up: np.ndarray
    region: ActionRegion
    means: np.ndarray
    whiten: np.ndarray
    opacities: np.ndarray
    reach: np.ndarray
    solid_means: np.ndarray
    solid_reach: np.ndarray
    near: float = NEAR_CLIP_M
    max_occlusion: float = MAX_OCCLUSION
    rig: Optional[RigVolume] = None
    track: Optional[np.ndarray] = None

    def with_track(self, means_over_time: np.ndarray, *, smooth: float = 3.0) -> "Framing":
        """Record where the subject is at every timestep: the per-axis median of its Gaussians' centres
        (``means_over_time`` (T,M,3), the subject's M Gaussians), smoothed over ``smooth`` timesteps
        (a Gaussian's sigma) so a camera following it does not shake. Returns self."""
        from scipy.ndimage import gaussian_filter1d

        pts = np.asarray(means_over_time, dtype=np.float64)
        centres = np.nanmedian(np.where(np.isfinite(pts), pts, np.nan), axis=1)
        if not np.isfinite(centres).all():
            return self
        self.track = gaussian_filter1d(centres, smooth, axis=0, mode="nearest") if len(centres) > 1 else centres
        return self

    def track_at(self, timesteps: np.ndarray) -> np.ndarray:
        """(n,3) the subject's (smoothed) centre at fractional ``timesteps`` (n,), linearly interpolated."""
        t = np.clip(np.asarray(timesteps, dtype=np.float64).reshape(-1), 0.0, len(self.track) - 1.0)
        return np.stack([np.interp(t, np.arange(len(self.track)), self.track[:, k]) for k in range(3)], axis=1)

    def within_rig(self, rig: Optional[RigVolume]) -> "Framing":
        """Keep framed cameras inside the volume the capture rig observed (:mod:`.rig_volume`): outside it
        lie the dome's back faces and whatever was never reconstructed. Returns self."""
        self.rig = rig
        return self

    def outside_rig(self, eyes: np.ndarray) -> np.ndarray:
        """(K,) how far (metres) each eye lies outside the rig volume (0 inside, or without a rig)."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        return np.zeros(len(eyes)) if self.rig is None else self.rig.outside(eyes)

    @property
    def centre(self) -> np.ndarray:
        return self.region.centre

    @staticmethod
    def build(means: np.ndarray, rotations: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
              relevancy: np.ndarray, up: np.ndarray, *, near: float = NEAR_CLIP_M,
              foreground: Optional[np.ndarray] = None, instance: int = 0) -> Optional["Framing"]:
        """Framing of one timestep, or None when nothing is relevant.

        Args:
            means: (N,3); rotations: (N,4) quaternions w,x,y,z; scales: (N,3) standard deviations;
            opacities: (N,) in [0,1]; relevancy: (N,) in [0,1]; up: (3,); foreground: (N,) bool or None;
            instance: which instance of the relevant Gaussians to frame (0: the largest relevancy mass).
        """
        means = np.asarray(means, dtype=np.float64)
        scales = np.maximum(np.nan_to_num(np.asarray(scales, dtype=np.float64), nan=1e-6), 1e-6)
        opacities = np.nan_to_num(np.asarray(opacities, dtype=np.float64), nan=0.0)
        region = action_region(means, relevancy, scales, opacities, up=up, foreground=foreground,
                               instance=instance)
        if region is None:
            return None
        finite = np.isfinite(means).all(axis=1)
        solid = (opacities >= MIN_OPACITY) & finite
        reach = SIGMAS * scales.max(axis=1)
        # Gaussians touching the action (the floor under the feet, a ball in hand) belong to the shot
        gap, _ = cKDTree(means[region.members]).query(np.where(finite[:, None], means, 0.0), k=1)
        away = gap > reach + float(np.median(reach[region.members]))
        obstacle = solid & ~region.members & away
        q = np.asarray(rotations, dtype=np.float64)[obstacle]
        q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
        R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix() if len(q) else np.zeros((0, 3, 3))
        whiten = np.swapaxes(R, 1, 2) / scales[obstacle][:, :, None]                 # diag(1/s) Rᵀ
        return Framing(up=np.asarray(up, dtype=np.float64), region=region, means=means[obstacle], whiten=whiten,
                       opacities=opacities[obstacle], reach=reach[obstacle], solid_means=means[solid],
                       solid_reach=reach[solid], near=float(near))

    def occlusion(self, eyes: np.ndarray, target: Optional[np.ndarray] = None) -> np.ndarray:
        """(K,) fraction in [0,1] of the view of ``target`` (default: the action centre) hidden from each
        eye (K,3) by obstacle Gaussians: ``1 - prod(1 - opacity * exp(-m²/2))`` over those whose 3-sigma
        ellipsoid the segment eye→target enters (``m`` its Mahalanobis distance from the segment)."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        target = self.centre if target is None else np.asarray(target, dtype=np.float64)
        out = np.zeros(len(eyes))
        if not len(self.means):
            return out
        for k, eye in enumerate(eyes):
            # cheap bounding-sphere test first: distance from each centre to the segment
            d = target - eye
            s = np.clip(((self.means - eye) @ d) / max(float(d @ d), 1e-300), 0.0, 1.0)
            near_seg = np.linalg.norm(self.means - (eye + s[:, None] * d), axis=1) <= self.reach
            idx = np.flatnonzero(near_seg)
            if not idx.size:
                continue
            m = _segment_mahalanobis(eye[None], target, self.means[idx], self.whiten[idx])[0]
            alpha = np.where(m <= SIGMAS, self.opacities[idx] * np.exp(-0.5 * m * m), 0.0)
            out[k] = 1.0 - float(np.prod(1.0 - np.clip(alpha, 0.0, 0.999)))
        return out

    def clearance(self, eyes: np.ndarray, target: Optional[np.ndarray] = None) -> np.ndarray:
        """(K,) distance from each eye (K,3), looking at ``target`` (default: the action centre), to the
        nearest 3-sigma sphere of a Gaussian that is not wholly behind it and lies within
        :data:`NEAR_CONE_SLOPE` of its view axis near the camera (where the near plane would cut it);
        +inf when there is none."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        target = self.centre if target is None else np.asarray(target, dtype=np.float64)
        out = np.full(len(eyes), np.inf)
        if not len(self.solid_means):
            return out
        for k, eye in enumerate(eyes):
            view, n = target - eye, float(np.linalg.norm(target - eye))
            if n <= 1e-12:
                out[k] = -np.inf
                continue
            rel = self.solid_means - eye
            depth = rel @ (view / n)
            dist = np.linalg.norm(rel, axis=1)
            lateral = np.sqrt(np.maximum(dist * dist - depth * depth, 0.0))
            reach = self.solid_reach
            seen = (depth + reach > 0) & (lateral - reach < NEAR_CONE_SLOPE * np.maximum(depth + reach, 0.0))
            if seen.any():
                out[k] = float((dist[seen] - reach[seen]).min())
        return out

    def path_problems(self, eyes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K,) occlusion and (K,) clearance of a path's camera positions."""
        return self.occlusion(eyes), self.clearance(eyes)

    def path_is_clear(self, eyes: np.ndarray) -> bool:
        """Every position sees the action centre (occlusion <= ``max_occlusion``) and keeps every
        Gaussian in view beyond the near plane (clearance >= ``near``)."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        if (self.outside_rig(eyes) > 0).any() or (self.clearance(eyes) < self.near).any():
            return False
        return bool((self.occlusion(eyes) <= self.max_occlusion).all())

    def path_enters_gaussians(self, eyes: np.ndarray) -> bool:
        """Whether a position of the path comes nearer a Gaussian in view than the near plane, or leaves the
        rig: frames there are filled with a splat's blur (an occluded action centre alone is not)."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        return bool((self.outside_rig(eyes) > 0).any() or (self.clearance(eyes) < self.near).any())

    def path_badness(self, eyes: np.ndarray) -> float:
        """How far a path is from clear (0 when :meth:`path_is_clear`): worst occlusion excess plus
        worst near-plane intrusion (metres); used to pick the least bad path when none is clear."""
        eyes = np.atleast_2d(np.asarray(eyes, dtype=np.float64))
        clr = self.clearance(eyes)
        near_bad = float(max(0.0, (self.near - clr).max()))
        occ = self.occlusion(eyes)
        return (float(max(0.0, (occ - self.max_occlusion).max())) + min(near_bad, 1e3)
                + float(self.outside_rig(eyes).max()))

    def fitting_focal(self, distance: float, resolution: Sequence[int], *, fill: float = 0.9) -> float:
        """Focal length (pixels) at which the region's sphere seen from ``distance`` spans ``fill`` of the
        image's shorter side (the inverse of :meth:`framing_distance`)."""
        ratio = min(self.region.radius / max(float(distance), 1e-9), 0.999)
        half = min(math.asin(ratio) / fill, math.radians(80.0))
        return 0.5 * min(resolution) / math.tan(half)

    def framing_distance(self, focal_px: float, resolution: Sequence[int], *, fill: float = 0.7) -> float:
        """Camera distance at which the region's sphere spans ``fill`` of the image's shorter side."""
        half = math.atan(0.5 * min(resolution) / max(float(focal_px), 1e-9))
        return self.region.radius / math.sin(max(half * fill, 1e-6))

    def nearest_clear_position(self, eye: np.ndarray, *, max_elevation_deg: float = 75.0) -> tuple[np.ndarray, bool]:
        """The position nearest to ``eye`` (turned about the up axis through the centre, raised, or
        pushed out — smallest change first) that sees the action clearly; ``eye`` itself when it does.
        Returns (position (3,), whether a clear one was found; else ``eye``)."""
        eye = np.asarray(eye, dtype=np.float64)
        if self.path_is_clear(eye[None]):
            return eye, True
        ez = self.up / np.linalg.norm(self.up)
        ex = np.eye(3)[int(np.argmin(np.abs(ez)))]
        ex = ex - (ex @ ez) * ez
        ex /= np.linalg.norm(ex)
        ey = np.cross(ez, ex)
        r = eye - self.centre
        az0, h0, z0 = math.atan2(r @ ey, r @ ex), math.hypot(r @ ex, r @ ey), float(r @ ez)
        d0, el0 = math.hypot(h0, z0), math.atan2(z0, h0)
        options = []
        for daz in range(-180, 181, 15):
            for del_ in (0, 10, 20, 30, 45):
                for ds in (1.0, 1.15, 1.3):
                    el = min(el0 + math.radians(del_), math.radians(max_elevation_deg))
                    options.append((abs(daz) / 90 + del_ / 45 + (ds - 1) * 3, math.radians(daz), el, d0 * ds))
        options.sort(key=lambda o: o[0])
        for _, daz, el, d in options:
            h = d * math.cos(el)
            p = self.centre + h * math.cos(az0 + daz) * ex + h * math.sin(az0 + daz) * ey + d * math.sin(el) * ez
            if self.path_is_clear(p[None]):
                return p, True
        return eye, False
