"""3D Gaussian Splatting PLY files (the Inria layout) via the ``plyfile`` package.

Vertex properties (Inria order)::

    x y z [nx ny nz] f_dc_0..2 [f_rest_0..M-1] opacity scale_0..2 rot_0..3

``f_rest`` holds the higher SH coefficients channel-major (all of red, then green, then blue), so
``M = 3 * ((deg+1)^2 - 1)`` for SH degree ``deg`` in 0..3. Opacity is a logit, scales are logs, the
rotation is a quaternion (w, x, y, z), stored unnormalized. Our SH array is ``(N, K, 3)``, DC first.

One file is a static scene (T=1); a directory of per-frame files (sorted naturally: ``frame_2`` before
``frame_10``) is a T-frame sequence with the same N in every file.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError, OutputExistsError
from ..fileio import atomic_path, read_json
from .camera import Camera, CameraRig
from .gaussians import GaussianSequence, normalize_quaternions_chunked, rgb_to_sh_dc
from .scene import Scene

ENCODINGS = {"binary_little_endian": (False, "<"), "binary_big_endian": (False, ">"), "ascii": (True, "=")}
SH_COEFFS_PER_DEGREE = {0: 1, 1: 4, 2: 9, 3: 16}
SPLAT_PROPERTIES = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass
class PlySplats:
    """The Gaussians of one PLY file (float32, as stored except for dtype).

    Attributes:
        means: (N,3).
        rotations: (N,4) quaternions w,x,y,z, unit length (normalized on read).
        log_scales: (N,3).
        opacity_logits: (N,).
        sh: (N,K,3) SH coefficients, K = (degree+1)^2, DC first.
        normals: (N,3) or None (3DGS writes zeros; kept only for a faithful round trip).
        file: where it was read from.
    """

    means: np.ndarray
    rotations: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    normals: Optional[np.ndarray] = None
    file: str = ""

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1


def natural_key(path: Path) -> list:
    """Sort key that orders embedded numbers numerically (``f2`` < ``f10``)."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


# --------------------------------------------------------------------------------------------- reading
def _read_vertex_table(path: Path) -> np.ndarray:
    import plyfile  # imported here so the engine imports without it until a PLY is read

    if not path.is_file():
        raise InputError("file is missing", file=path)
    try:
        ply = plyfile.PlyData.read(str(path))
    except plyfile.PlyParseError as exc:
        raise InputError(f"corrupt or truncated PLY file ({exc})", file=path) from None
    except (ValueError, UnicodeDecodeError, EOFError, OSError, IndexError, KeyError) as exc:
        raise InputError(f"corrupt or truncated PLY file ({type(exc).__name__}: {exc})", file=path) from None
    except MemoryError:
        raise InputError(f"its header claims more vertices than fit in memory ({path.stat().st_size} bytes of "
                         "file): damaged, or not a splat file", file=path, field="vertex") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise InputError(f"has no 'vertex' element (elements: {names or 'none'})", file=path, field="vertex")
    return ply["vertex"].data


def _column(table: np.ndarray, name: str, path: Path) -> np.ndarray:
    col = table[name]
    if col.dtype.hasobject:
        raise InputError("is a list property, expected one number per vertex", file=path, field=name)
    if not (np.issubdtype(col.dtype, np.floating) or np.issubdtype(col.dtype, np.integer)):
        raise InputError(f"has type {col.dtype}, expected a number", file=path, field=name)
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.asarray(col, dtype=np.float32)
    if not np.isfinite(out).all():
        bad = int(np.argwhere(~np.isfinite(out))[0, 0])
        what = "NaN or Inf" if not np.isfinite(col[bad]) else f"a value too large for float32 ({col[bad]:g})"
        raise InputError(f"contains {what} (first at vertex {bad})", file=path, field=name)
    return out


def _columns(table: np.ndarray, names: Sequence[str], path: Path) -> np.ndarray:
    """Stack properties as (N, len(names)) float32."""
    if not names:
        return np.zeros((table.shape[0], 0), np.float32)
    return np.stack([_column(table, n, path) for n in names], axis=1)


def _indexed(props: set[str], prefix: str) -> list[int]:
    pat = re.compile(re.escape(prefix) + r"(\d+)$")
    return sorted(int(m.group(1)) for p in props if (m := pat.match(p)))


def read_ply_splats(path: str | Path) -> PlySplats:
    """Read one 3DGS PLY (binary little/big-endian or ASCII, SH degree 0..3, normals optional).

    Raises:
        InputError: missing file; corrupt or truncated file; a plain point cloud (no splat properties);
            a missing or malformed property; NaN/Inf values; a zero-length quaternion.
    Warns when quaternions were not unit length (they are normalized).
    """
    path = Path(path)
    table = _read_vertex_table(path)
    props = set(table.dtype.names or ())
    missing_xyz = [p for p in ("x", "y", "z") if p not in props]
    if missing_xyz:
        raise InputError(f"missing vertex properties {missing_xyz}", file=path, field="vertex")
    missing = [p for p in SPLAT_PROPERTIES if p not in props]
    if len(missing) == len(SPLAT_PROPERTIES):
        raise InputError("is a point cloud, not Gaussian splats: the vertices have no "
                         f"{', '.join(SPLAT_PROPERTIES)} properties", file=path, field="vertex")
    dc_missing = [f"f_dc_{i}" for i in range(3) if f"f_dc_{i}" not in props]
    if missing or dc_missing:
        raise InputError(f"missing Gaussian splat properties {missing + dc_missing}", file=path, field="vertex")
    if table.shape[0] == 0:
        raise InputError("has no vertices (0 Gaussians)", file=path, field="vertex")

    rest = _indexed(props, "f_rest_")
    if rest != list(range(len(rest))):
        raise InputError(f"f_rest_* indices are not contiguous from 0 (found {rest[:5]}...)", file=path,
                         field="f_rest")
    coeffs = {3 * (k - 1): deg for deg, k in SH_COEFFS_PER_DEGREE.items()}
    if len(rest) not in coeffs:
        raise InputError(f"has {len(rest)} f_rest coefficients; expected 0, 9, 24 or 45 (SH degree 0..3)",
                         file=path, field="f_rest")
    K = SH_COEFFS_PER_DEGREE[coeffs[len(rest)]]

    means = _columns(table, ("x", "y", "z"), path)
    dc = _columns(table, ("f_dc_0", "f_dc_1", "f_dc_2"), path)
    f_rest = _columns(table, [f"f_rest_{i}" for i in rest], path)
    sh = np.empty((means.shape[0], K, 3), np.float32)
    sh[:, 0, :] = dc
    sh[:, 1:, :] = f_rest.reshape(means.shape[0], 3, K - 1).transpose(0, 2, 1)  # channel-major -> (N,K-1,3)
    has_normals = all(n in props for n in ("nx", "ny", "nz"))
    rot = _columns(table, ("rot_0", "rot_1", "rot_2", "rot_3"), path)
    return PlySplats(
        means=means,
        rotations=normalize_quaternions_chunked(rot, file=str(path), field="rot_0..3"),
        log_scales=_columns(table, ("scale_0", "scale_1", "scale_2"), path),
        opacity_logits=_column(table, "opacity", path),
        sh=sh,
        normals=_columns(table, ("nx", "ny", "nz"), path) if has_normals else None,
        file=str(path),
    )


# --------------------------------------------------------------------------------------------- writing
def write_ply_splats(path: str | Path, means: np.ndarray, rotations: np.ndarray, log_scales: np.ndarray,
                     opacity_logits: np.ndarray, sh: np.ndarray, normals: Optional[np.ndarray] = None, *,
                     encoding: str = "binary_little_endian", overwrite: bool = False) -> Path:
    """Write one 3DGS PLY atomically in the Inria property order.

    Args:
        means (N,3), rotations (N,4) w,x,y,z, log_scales (N,3), opacity_logits (N,), sh (N,K,3) with
        K in 1,4,9,16, normals (N,3) or None (omitted), encoding: binary_little_endian (default),
        binary_big_endian or ascii.
    """
    import plyfile

    path = Path(path)
    if encoding not in ENCODINGS:
        raise InputError(f"unknown PLY encoding {encoding!r} (choose {', '.join(ENCODINGS)})", field="encoding")
    sh = np.asarray(sh)
    N = int(np.asarray(means).shape[0])
    if sh.ndim != 3 or sh.shape[0] != N or sh.shape[2] != 3 or sh.shape[1] not in SH_COEFFS_PER_DEGREE.values():
        raise InputError(f"has shape {sh.shape}, expected (N={N},K,3) with K in 1,4,9,16", field="sh")
    K = sh.shape[1]
    columns: list[tuple[str, np.ndarray]] = []
    columns += [(n, np.asarray(means)[:, i]) for i, n in enumerate("xyz")]
    if normals is not None:
        columns += [(n, np.asarray(normals)[:, i]) for i, n in enumerate(("nx", "ny", "nz"))]
    columns += [(f"f_dc_{c}", sh[:, 0, c]) for c in range(3)]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(N, 3 * (K - 1))  # (N,K-1,3) -> channel-major
    columns += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    columns += [("opacity", np.asarray(opacity_logits).reshape(N))]
    columns += [(f"scale_{i}", np.asarray(log_scales)[:, i]) for i in range(3)]
    columns += [(f"rot_{i}", np.asarray(rotations)[:, i]) for i in range(4)]
    text, byte_order = ENCODINGS[encoding]
    table = np.empty(N, dtype=[(name, byte_order + "f4" if not text else "f4") for name, _ in columns])
    for name, col in columns:
        table[name] = col
    element = plyfile.PlyElement.describe(table, "vertex")
    data = plyfile.PlyData([element], text=text, byte_order=byte_order)
    with atomic_path(path, overwrite=overwrite) as tmp:
        data.write(str(tmp))
    return path


def write_ply_scene(scene: Scene, path: str | Path, *, encoding: str = "binary_little_endian",
                    overwrite: bool = False) -> Path:
    """Export a scene as PLY: ``*.ply`` path -> one file (needs T=1); else a directory of
    ``frame_000000.ply``... (one per timestep). Colours-only scenes are written as SH degree 0."""
    path = Path(path)
    g = scene.gaussians
    single = path.suffix.lower() == ".ply"
    if single and g.num_timesteps != 1:
        raise InputError(f"one PLY file holds one timestep, the scene has {g.num_timesteps}; give a directory",
                         file=path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    targets = [path] if single else [path / f"frame_{t:06d}.ply" for t in range(g.num_timesteps)]
    for t, target in enumerate(targets):
        if g.sh is not None:
            sh = np.asarray(g.sh[t] if g.sh.ndim == 4 else g.sh)
        else:
            sh = rgb_to_sh_dc(np.asarray(g.colors[t] if g.colors.ndim == 3 else g.colors))[:, None, :]
        write_ply_splats(target, g.means[t], g.rotations[t],
                         g.log_scales[t] if g.log_scales.ndim == 3 else g.log_scales, g.opacity_logits, sh,
                         encoding=encoding, overwrite=True)
    return path


# ------------------------------------------------------------------------------------------ to a Scene
def _same(frames: list[np.ndarray]) -> bool:
    return all(np.array_equal(frames[0], f) for f in frames[1:])


def ply_frames_to_sequence(frames: list[PlySplats], source: str) -> GaussianSequence:
    """Stack per-frame splats (same N) into a sequence; static fields are stored once when equal."""
    first = frames[0]
    for f in frames[1:]:
        if f.num_gaussians != first.num_gaussians:
            raise InputError(f"has {f.num_gaussians} Gaussians but {Path(first.file).name} has "
                             f"{first.num_gaussians}; every frame needs the same N", file=f.file, field="vertex")
        if f.sh.shape[1] != first.sh.shape[1]:
            raise InputError(f"has SH degree {f.sh_degree} but {Path(first.file).name} has degree "
                             f"{first.sh_degree}", file=f.file, field="f_rest")
    opac = [f.opacity_logits for f in frames]
    if not _same(opac):
        warnings.warn(f"{source}: opacity differs between frames; the scene model has static opacity, "
                      f"so {Path(first.file).name}'s is used", stacklevel=3)
    scales = [f.log_scales for f in frames]
    shs = [f.sh for f in frames]
    return GaussianSequence(
        means=np.stack([f.means for f in frames]),
        rotations=np.stack([f.rotations for f in frames]),
        log_scales=scales[0] if _same(scales) else np.stack(scales),
        opacity_logits=first.opacity_logits,
        sh=shs[0] if _same(shs) else np.stack(shs),
        source=source,
    )


def load_ply_scene(path: str | Path) -> Scene:
    """A single PLY file as a static scene (T=1); Inria ``cameras.json`` is used when found."""
    path = Path(path)
    splats = read_ply_splats(path)
    g = ply_frames_to_sequence([splats], str(path))
    return Scene(gaussians=g, cameras=find_inria_cameras(path, 1), name=_scene_name(path), root=None,
                 metadata={"source_format": "3dgs-ply", "source": str(path), "sh_degree": splats.sh_degree})


def ply_frame_files(directory: str | Path) -> list[Path]:
    directory = Path(directory)
    files = sorted((p for p in directory.iterdir() if p.suffix.lower() == ".ply" and p.is_file()), key=natural_key)
    if not files:
        raise InputError("contains no .ply files", file=directory)
    return files


def load_ply_sequence(directory: str | Path) -> Scene:
    """A directory of per-frame PLY files (natural sort order) as a T-frame scene."""
    directory = Path(directory)
    files = ply_frame_files(directory)
    frames = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for f in files:
            frames.append(read_ply_splats(f))
    if any("not unit length" in str(w.message) for w in caught):
        warnings.warn(f"{directory}: rot_0..3: quaternions were not unit length; normalized", stacklevel=2)
    for w in caught:
        if "not unit length" not in str(w.message):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    g = ply_frames_to_sequence(frames, str(directory))
    return Scene(gaussians=g, cameras=find_inria_cameras(directory, len(files)), name=directory.name,
                 metadata={"source_format": "3dgs-ply-sequence", "source": str(directory),
                           "frames": [f.name for f in files], "sh_degree": frames[0].sh_degree})


def _scene_name(path: Path) -> str:
    # Inria layout: <model>/point_cloud/iteration_30000/point_cloud.ply -> <model>
    if path.parent.name.startswith("iteration_") and path.parent.parent.name == "point_cloud":
        return path.parent.parent.parent.name
    return path.stem


def find_inria_cameras(path: Path, num_timesteps: int) -> CameraRig:
    """Cameras from the Inria ``cameras.json`` next to the PLY (or at the model root), else no cameras.

    Each entry: ``width``, ``height``, ``position`` (camera centre), ``rotation`` (3x3 camera-to-world
    rotation, OpenCV axes), ``fx``, ``fy``; principal point at the image centre. All go to ``train``.
    """
    candidates = [path.parent / "cameras.json", path / "cameras.json"]
    if path.parent.name.startswith("iteration_"):
        candidates.append(path.parent.parent.parent / "cameras.json")
    file = next((c for c in candidates if c.is_file()), None)
    if file is None:
        return CameraRig.static([], [], num_timesteps)
    entries = read_json(file)
    if not isinstance(entries, list):
        raise InputError("expected a JSON list of cameras", file=file)
    cams = []
    for i, e in enumerate(entries):
        try:
            R = np.asarray(e["rotation"], dtype=np.float64)
            C = np.asarray(e["position"], dtype=np.float64)
            w, h = int(e["width"]), int(e["height"])
            K = np.array([[float(e["fx"]), 0, w / 2.0], [0, float(e["fy"]), h / 2.0], [0, 0, 1]])
        except KeyError as exc:
            raise InputError(f"missing key {exc}", file=file, field=f"[{i}]") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"malformed camera ({exc})", file=file, field=f"[{i}]") from None
        if R.shape != (3, 3) or C.shape != (3,):
            raise InputError("rotation must be 3x3 and position a 3-vector", file=file, field=f"[{i}]")
        w2c = np.eye(4)
        w2c[:3, :3] = R.T
        w2c[:3, 3] = -R.T @ C
        cams.append(Camera(K=K, w2c=w2c, width=w, height=h, name=str(e.get("img_name", e.get("id", i))))
                    .validate(str(file), f"[{i}]"))
    return CameraRig.static(cams, [], num_timesteps)
