"""Dynamic 3D Gaussians (Luiten et al.) scenes: ``params.npz`` + ``train_meta.json`` / ``test_meta.json``.

``params.npz`` keys (T timesteps, N Gaussians)::

    means3D (T,N,3)  rgb_colors (T,N,3)  unnorm_rotations (T,N,4) w,x,y,z     -- per timestep
    logit_opacities (N,1)  log_scales (N,3)  [seg_colors (N,3)]  [cam_m (C,3)  cam_c (C,3)]  -- static

Foreground is ``seg_colors[:,0] > 0.5``; ``cam_m``/``cam_c`` (per-camera colour correction
``exp(cam_m) * img + cam_c``) are kept in ``scene.metadata["color_correction"]``.

Camera metadata (``*_meta.json``): ``w``, ``h``, ``k[t][c]`` (3x3), ``w2c[t][c]`` (4x4, OpenCV),
``fn[t][c]``, ``cam_id[t][c]``. Camera names come from ``cam_id``.

No pickle is ever executed: members of uncompressed archives are memory-mapped after their ``.npy``
header is checked (object dtypes refused), compressed members go through
``np.load(allow_pickle=False)``, and a file that is a pickle rather than a zip archive is refused.
"""
from __future__ import annotations

import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath
from typing import Any, Optional

import numpy as np

from ..errors import InputError, OutputExistsError
from ..fileio import NPY_HEADER_ERRORS, atomic_directory, atomic_path, read_json, write_json_atomic
from .camera import MAX_IMAGE_SIDE, Camera, CameraRig
from .gaussians import GaussianSequence, normalize_quaternions_chunked, sh_dc_to_rgb
from .scene import Scene

PARAMS_FILE = "params.npz"
META_FILES = {"train": "train_meta.json", "test": "test_meta.json"}
REQUIRED_KEYS = ("means3D", "rgb_colors", "unnorm_rotations", "logit_opacities", "log_scales")
PICKLE_MAGIC = b"\x80"


# ------------------------------------------------------------------------------------ safe npz reading
class NpzArrays:
    """Read-only access to the arrays of an ``.npz`` file without ever unpickling.

    ``arrays[name]`` returns a read-only memory map for uncompressed members (the usual
    ``np.savez`` output) and an in-memory array for compressed ones.
    """

    def __init__(self, path: Path):
        self.path = path
        if not path.is_file():
            raise InputError("file is missing", file=path)
        with open(path, "rb") as fh:
            head = fh.read(4)
        if head[:1] == PICKLE_MAGIC:
            raise InputError("is a Python pickle, not an .npz archive; pickles are refused (never unpickled)",
                             file=path)
        try:
            self._zip = zipfile.ZipFile(path)
            self._infos = {info.filename: info for info in self._zip.infolist()}
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise InputError(f"corrupt or truncated .npz archive ({exc})", file=path) from None
        self.keys = [n[:-4] for n in self._infos if n.endswith(".npy")]

    def close(self) -> None:
        self._zip.close()

    def __contains__(self, key: str) -> bool:
        return key in self.keys

    def __getitem__(self, key: str) -> np.ndarray:
        info = self._infos.get(key + ".npy")
        if info is None:
            raise InputError(f"missing key (present: {', '.join(sorted(self.keys)) or 'none'})",
                             file=self.path, field=key)
        try:
            if info.compress_type == zipfile.ZIP_STORED and not info.flag_bits & 0x1:
                mapped = self._memmap_member(info, key)
                if mapped is not None:
                    return mapped
            with self._zip.open(info) as member:
                return np.load(member, allow_pickle=False)
        except ValueError as exc:
            if "pickle" in str(exc).lower() or "object" in str(exc).lower():
                raise InputError("holds an object/pickled array, which is refused (never unpickled)",
                                 file=self.path, field=key) from None
            raise InputError(f"corrupt array ({exc})", file=self.path, field=key) from None
        except MemoryError:
            raise InputError("its header claims an array larger than memory (damaged)", file=self.path,
                             field=key) from None
        except (zipfile.BadZipFile, struct.error, RuntimeError, NotImplementedError) + NPY_HEADER_ERRORS as exc:
            # RuntimeError: encrypted entry; NotImplementedError: unsupported compression method
            raise InputError(f"corrupt, truncated or unreadable array ({exc})", file=self.path, field=key) from None

    def _memmap_member(self, info: zipfile.ZipInfo, key: str) -> Optional[np.ndarray]:
        with open(self.path, "rb") as fh:
            fh.seek(info.header_offset)
            local = fh.read(30)
            if len(local) < 30 or local[:4] != b"PK\x03\x04":
                raise InputError("corrupt archive entry (bad local header)", file=self.path, field=key)
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            start = info.header_offset + 30 + name_len + extra_len
            fh.seek(start)
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                return None  # rare header versions: let np.load (allow_pickle=False) handle them
            if dtype.hasobject:
                raise InputError("holds an object/pickled array, which is refused (never unpickled)",
                                 file=self.path, field=key)
            offset = fh.tell()
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if offset - start + nbytes > info.file_size or len(shape) == 0 or nbytes == 0:
            if offset - start + nbytes > info.file_size:
                raise InputError(f"truncated array: header promises {nbytes} bytes, the entry holds "
                                 f"{info.file_size - (offset - start)}", file=self.path, field=key)
            return None
        if offset + nbytes > self.path.stat().st_size:
            raise InputError("truncated file: the array runs past the end of the file", file=self.path, field=key)
        return np.memmap(self.path, dtype=dtype, mode="r", offset=offset, shape=shape,
                         order="F" if fortran else "C")


# ---------------------------------------------------------------------------------------- validation
def _float_array(arrays: NpzArrays, key: str, shapes: list[tuple[int, ...]], labels: str) -> np.ndarray:
    arr = arrays[key]
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"has dtype {arr.dtype}, expected a float type", file=arrays.path, field=key)
    if tuple(arr.shape) not in shapes:
        raise InputError(f"has shape {tuple(arr.shape)}, expected {labels}", file=arrays.path, field=key)
    _check_finite(arr, arrays.path, key)
    return arr


def _check_finite(arr: np.ndarray, file: Path | str, key: str, chunk: int = 1 << 22) -> None:
    flat = arr.reshape(-1)
    for s in range(0, flat.shape[0], chunk):
        block = np.asarray(flat[s:s + chunk])
        if not np.isfinite(block).all():
            idx = np.unravel_index(s + int(np.argmax(~np.isfinite(block))), arr.shape)
            raise InputError(f"contains NaN or Inf (first at index {[int(i) for i in idx]})", file=file, field=key)


def read_params(path: str | Path) -> dict[str, Any]:
    """Read and validate ``params.npz``. Returns our field names -> arrays (+ ``cam_m``/``cam_c``)."""
    path = Path(path)
    arrays = NpzArrays(path)
    try:
        for key in REQUIRED_KEYS:
            if key not in arrays:
                raise InputError(f"missing key (present: {', '.join(sorted(arrays.keys)) or 'none'})",
                                 file=path, field=key)
        means = arrays["means3D"]
        if means.ndim != 3 or means.shape[2] != 3:
            raise InputError(f"has shape {tuple(means.shape)}, expected (T,N,3)", file=path, field="means3D")
        T, N = int(means.shape[0]), int(means.shape[1])
        if T < 1 or N < 1:
            raise InputError(f"has shape {tuple(means.shape)}: needs at least one timestep and one Gaussian",
                             file=path, field="means3D")
        tn = f"(T={T}, N={N}"
        out: dict[str, Any] = {
            "means": _float_array(arrays, "means3D", [(T, N, 3)], tn + ", 3)"),
            "colors": _float_array(arrays, "rgb_colors", [(T, N, 3), (N, 3)], tn + ", 3)"),
            "log_scales": _float_array(arrays, "log_scales", [(N, 3), (T, N, 3)], f"(N={N}, 3) or {tn}, 3)"),
        }
        rot = _float_array(arrays, "unnorm_rotations", [(T, N, 4)], tn + ", 4)")
        out["rotations"] = normalize_quaternions_chunked(rot, file=str(path), field="unnorm_rotations")
        opac = _float_array(arrays, "logit_opacities", [(N, 1), (N,)], f"(N={N}, 1)")
        out["opacity_logits"] = np.asarray(opac, dtype=np.float32).reshape(N)
        if "seg_colors" in arrays:
            seg = _float_array(arrays, "seg_colors", [(N, 3)], f"(N={N}, 3)")
            out["foreground"] = np.asarray(seg[:, 0]) > 0.5
        for key in ("cam_m", "cam_c"):
            if key in arrays:
                arr = arrays[key]
                if arr.ndim != 2 or arr.shape[1] != 3:
                    raise InputError(f"has shape {tuple(arr.shape)}, expected (C,3)", file=path, field=key)
                out[key] = _float_array(arrays, key, [tuple(arr.shape)], "(C,3)")
        return out
    finally:
        arrays.close()


@dataclass
class CameraMeta:
    """One ``*_meta.json`` file: cameras ``[t][c]``, their image files ``fn[t][c]`` (relative to ``ims/``;
    None when the file lists none), their names ``[t][c]`` and the image size shared by every camera."""

    cameras: list[list[Camera]]
    files: Optional[list[list[str]]]
    names: list[list[str]]
    width: int
    height: int


def read_meta(path: Path, T: int) -> list[list[Camera]]:
    """Cameras ``[t][c]`` of a scene's ``*_meta.json`` file, validated against the scene's T."""
    return read_camera_meta(path, num_timesteps=(T, "params.npz")).cameras


def read_camera_meta(path: Path, *, num_timesteps: Optional[tuple[int, str]] = None, require_files: bool = False,
                     static_rig: bool = False, near: float = 0.01, far: float = 100.0) -> CameraMeta:
    """Read and check a ``*_meta.json`` file (the module docstring has the layout); every problem is one
    InputError naming the file and the field.

    ``num_timesteps``: (T, where T comes from) every per-timestep list must match (default: ``k``'s length).
    ``require_files``: ``fn`` must be present (a capture's images). ``static_rig``: the same cameras at every
    timestep. Camera names are ``cam_id``, else the folder of ``fn``, else the camera's index.
    """
    meta: Any = read_json(path)
    if not isinstance(meta, dict):
        raise InputError("top level must be a JSON object", file=path)
    for key in ("w", "h", "k", "w2c") + (("fn",) if require_files else ()):
        if key not in meta:
            raise InputError("missing key", file=path, field=key)
    width, height = _image_size(meta, path)
    ks, w2cs, fns, ids = meta["k"], meta["w2c"], meta.get("fn"), meta.get("cam_id")
    T, source = num_timesteps if num_timesteps is not None else (len(ks) if isinstance(ks, list) else -1, "")
    for key, value in (("k", ks), ("w2c", w2cs), ("fn", fns), ("cam_id", ids)):
        if value is None:
            continue
        if not isinstance(value, list) or (not value and num_timesteps is None):
            raise InputError("must be a non-empty list over timesteps", file=path, field=key)
        if len(value) != T:
            raise InputError(f"has {len(value)} timesteps but {source} has T={T}" if source else
                             f"has {len(value)} timesteps, k has {T}", file=path, field=key)
    cameras, names = [], []
    for t in range(T):
        if not isinstance(ks[t], list):
            raise InputError("must be a list of 3x3 matrices, one per camera", file=path, field=f"k[{t}]")
        n = len(ks[t])
        for key, lists in (("w2c", w2cs), ("fn", fns), ("cam_id", ids)):
            if lists is not None and (not isinstance(lists[t], list) or len(lists[t]) != n):
                raise InputError(f"must list one entry per camera ({n})", file=path, field=f"{key}[{t}]")
        row = [_meta_camera(meta, t, c, path, width, height, near, far) for c in range(n)]
        if len({cam.name for cam in row}) != len(row):
            raise InputError("camera ids repeat", file=path, field=f"cam_id[{t}]")
        if static_rig and t and [cam.name for cam in row] != names[0]:
            raise InputError(f"cameras differ from timestep 0 ({[cam.name for cam in row]} vs {names[0]})",
                             file=path, field=f"cam_id[{t}]")
        cameras.append(row)
        names.append([cam.name for cam in row])
    files = [[str(f) for f in fns[t]] for t in range(T)] if fns is not None else None
    return CameraMeta(cameras, files, names, width, height)


def _image_size(meta: dict[str, Any], path: Path) -> tuple[int, int]:
    """``w``, ``h``: positive integers within the image size any camera may have."""
    try:
        width, height = int(meta["w"]), int(meta["h"])
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"image size must be integers, got w={meta['w']!r} h={meta['h']!r}", file=path,
                         field="w/h") from None
    if width <= 0 or height <= 0:
        raise InputError(f"image size must be positive, got {width}x{height}", file=path, field="w/h")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise InputError(f"image size must be at most {MAX_IMAGE_SIDE} pixels a side, got w={meta['w']!r} "
                         f"h={meta['h']!r}", file=path, field="w/h")
    return width, height


def _meta_camera(meta: dict[str, Any], t: int, c: int, path: Path, width: int, height: int, near: float,
                 far: float) -> Camera:
    """Camera ``c`` of timestep ``t``: finite matrices, positive focal lengths, a valid pose."""
    K = meta_matrix(meta["k"][t][c], (3, 3), path, f"k[{t}][{c}]")
    w2c = meta_matrix(meta["w2c"][t][c], (4, 4), path, f"w2c[{t}][{c}]")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"focal length must be positive (fx={K[0, 0]}, fy={K[1, 1]})", file=path,
                         field=f"k[{t}][{c}]")
    fn = meta["fn"][t][c] if meta.get("fn") is not None else None
    if fn is not None and (not isinstance(fn, str) or not fn or ".." in Path(fn).parts or Path(fn).is_absolute()
                           or PureWindowsPath(fn).anchor or "\x00" in fn):
        raise InputError(f"must be a file name relative to the capture (no '..', not absolute), got {fn!r}",
                         file=path, field=f"fn[{t}][{c}]")
    ids = meta.get("cam_id")
    name = str(ids[t][c]) if ids is not None else fn.split("/")[0] if fn is not None else str(c)
    cam = Camera(K=K, w2c=w2c, width=width, height=height, near=near, far=far, name=name)
    try:
        cam.validate()
    except InputError as exc:
        where = f"w2c[{t}][{c}]" if "w2c" in (exc.field or "") else f"k[{t}][{c}]"
        raise InputError(f"{exc.problem} (camera {name})", file=path, field=where) from None
    return cam


def meta_matrix(value: Any, shape: tuple[int, int], file: Path, field: str) -> np.ndarray:
    """A finite float64 matrix of ``shape`` read from camera metadata (else InputError naming file/field)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"is not a numeric {shape[0]}x{shape[1]} matrix", file=file, field=field) from None
    if arr.shape != shape:
        raise InputError(f"has shape {arr.shape}, expected {shape}", file=file, field=field)
    if not np.isfinite(arr).all():
        raise InputError("contains NaN or Inf", file=file, field=field)
    return arr


def is_dynamic3dgs(path: str | Path) -> bool:
    return (Path(path) / PARAMS_FILE).is_file()


def load_dynamic3dgs(path: str | Path, *, meta_dir: str | Path | None = None,
                     params_file: str | Path | None = None) -> Scene:
    """Load a Dynamic 3D Gaussians scene directory (``params.npz`` + optional ``*_meta.json``).

    Args:
        path: the directory holding ``params.npz`` (and usually the meta files).
        meta_dir: where ``train_meta.json`` / ``test_meta.json`` live, if elsewhere (the original
            code keeps them with the dataset, not the trained model). Missing meta -> no cameras.
        params_file: an explicit ``.npz`` path instead of ``path/params.npz``.
    """
    path = Path(path)
    if not path.is_dir():
        raise InputError("is not a directory", file=path)
    params_path = Path(params_file) if params_file is not None else path / PARAMS_FILE
    params = read_params(params_path)
    T = int(params["means"].shape[0])
    meta_root = Path(meta_dir) if meta_dir is not None else path
    splits = {s: read_meta(meta_root / f, T) if (meta_root / f).is_file() else [] for s, f in META_FILES.items()}
    metadata: dict[str, Any] = {"source_format": "dynamic3dgs", "source": str(params_path),
                                "camera_meta": [f for s, f in META_FILES.items() if splits[s]]}
    if "cam_m" in params or "cam_c" in params:
        metadata["color_correction"] = {k: np.asarray(params.pop(k), dtype=np.float64).tolist()
                                        for k in ("cam_m", "cam_c") if k in params}
    g = GaussianSequence(source=str(params_path), **params)
    return Scene(gaussians=g, cameras=CameraRig(train=splits["train"], test=splits["test"]), name=path.name,
                 fps=30.0, root=None, metadata=metadata)


# --------------------------------------------------------------------------------------------- writing
def write_dynamic3dgs(scene: Scene, path: str | Path, *, overwrite: bool = False, compressed: bool = False) -> Path:
    """Export ``scene`` as a Dynamic 3D Gaussians directory (atomically; refuses to overwrite).

    Colours: ``colors`` as stored (broadcast to (T,N,3) when static), else RGB from the SH DC term.
    Foreground becomes ``seg_colors = [fg, 0, 1-fg]`` (omitted when the scene has none); cameras go to
    ``train_meta.json`` / ``test_meta.json`` (omitted when a split is empty); colour correction from
    ``scene.metadata["color_correction"]``.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    g = scene.gaussians
    T, N = g.num_timesteps, g.num_gaussians
    if g.colors is not None:
        colors = np.asarray(g.colors, dtype=np.float32)
        colors = colors if colors.ndim == 3 else np.broadcast_to(colors, (T, N, 3))
    else:
        colors = np.stack([sh_dc_to_rgb(np.asarray(g.sh[t] if g.sh.ndim == 4 else g.sh)[:, 0, :])
                           for t in range(T)]).astype(np.float32)
    arrays: dict[str, np.ndarray] = {
        "means3D": np.asarray(g.means, dtype=np.float32),
        "rgb_colors": np.ascontiguousarray(colors),
        "unnorm_rotations": np.asarray(g.rotations, dtype=np.float32),
        "logit_opacities": np.asarray(g.opacity_logits, dtype=np.float32).reshape(N, 1),
        "log_scales": np.asarray(g.log_scales, dtype=np.float32),
    }
    if g.foreground is not None:
        fg = np.asarray(g.foreground, dtype=np.float32)
        arrays["seg_colors"] = np.stack([fg, np.zeros_like(fg), 1.0 - fg], axis=1)
    for key, value in (scene.metadata.get("color_correction") or {}).items():
        arrays[key] = np.asarray(value, dtype=np.float32)
    with atomic_directory(path, overwrite=overwrite) as tmp:
        with atomic_path(tmp / PARAMS_FILE) as part:
            with open(part, "wb") as fh:
                (np.savez_compressed if compressed else np.savez)(fh, **arrays)
        for split, file in META_FILES.items():
            lists = scene.cameras.train if split == "train" else scene.cameras.test
            if any(lists):
                write_json_atomic(tmp / file, _meta_dict(lists, T, file))
    return path


def _meta_dict(lists: list[list[Camera]], T: int, file: str) -> dict[str, Any]:
    if len(lists) != T:
        raise InputError(f"the camera rig covers {len(lists)} timesteps, the scene {T}", field=file)
    sizes = {(c.width, c.height) for l in lists for c in l}
    if len(sizes) != 1:
        raise InputError(f"all cameras need one image size in this format, found {sorted(sizes)}", field=file)
    (w, h), = sizes
    return {"w": w, "h": h,
            "k": [[c.K.tolist() for c in l] for l in lists],
            "w2c": [[c.w2c.tolist() for c in l] for l in lists],
            "fn": [[f"{c.name}/{t:06d}.jpg" for c in l] for t, l in enumerate(lists)],
            "cam_id": [[_cam_id(c.name) for c in l] for l in lists]}


def _cam_id(name: str) -> int | str:
    return int(name) if name.isdigit() else name
