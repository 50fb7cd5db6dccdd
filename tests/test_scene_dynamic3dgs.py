"""Dynamic 3D Gaussians (params.npz + *_meta.json): round trip, hand-made files, every bad input."""
from __future__ import annotations

import json
import pickle
import warnings

import numpy as np
import pytest

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.scene import Camera, CameraRig, Scene, load_scene
from fourlegs_engine.scene.dynamic3dgs import load_dynamic3dgs, write_dynamic3dgs

from _scene_helpers import (assert_rigs_equal, assert_sequences_equal, random_scene, random_sequence,
                            random_unit_quaternions)

T, N = 3, 6


def _params(seed=0):
    rng = np.random.default_rng(seed)
    return {"means3D": rng.normal(size=(T, N, 3)).astype(np.float32),
            "rgb_colors": rng.random((T, N, 3)).astype(np.float32),
            "unnorm_rotations": random_unit_quaternions(rng, (T, N)),
            "logit_opacities": rng.normal(size=(N, 1)).astype(np.float32),
            "log_scales": rng.normal(-3, 1, size=(N, 3)).astype(np.float32),
            "seg_colors": np.stack([np.arange(N) % 2, np.zeros(N), 1 - np.arange(N) % 2], 1).astype(np.float32),
            "cam_m": rng.normal(0, 0.1, size=(50, 3)).astype(np.float32),
            "cam_c": rng.normal(0, 0.1, size=(50, 3)).astype(np.float32)}


def _meta(num_t=T, cams=2):
    rig = [[Camera.look_at((3 * np.cos(c + 0.1 * t), 3 * np.sin(c), 1.0), (0, 0, 0), width=64, height=36,
                           focal=50.0 + c) for c in range(cams)] for t in range(num_t)]
    return {"w": 64, "h": 36, "k": [[c.K.tolist() for c in l] for l in rig],
            "w2c": [[c.w2c.tolist() for c in l] for l in rig],
            "fn": [[f"{5 * c + 1}/{t:06d}.jpg" for c in range(cams)] for t in range(num_t)],
            "cam_id": [[5 * c + 1 for c in range(cams)] for t in range(num_t)]}


def _write(tmp_path, params=None, train=None, test=None, compressed=False):
    d = tmp_path / "seq"
    d.mkdir(exist_ok=True)
    params = _params() if params is None else params
    (np.savez_compressed if compressed else np.savez)(d / "params.npz", **params)
    (d / "train_meta.json").write_text(json.dumps(_meta() if train is None else train))
    if test is not False:
        (d / "test_meta.json").write_text(json.dumps(_meta(cams=1) if test is None else test))
    return d


@pytest.mark.parametrize("compressed", [False, True])
def test_hand_made_scene_is_read_as_documented(tmp_path, compressed):
    p = _params()
    p["unnorm_rotations"] *= np.float32(2.5)  # Dynamic 3D Gaussians stores them unnormalized
    d = _write(tmp_path, p, compressed=compressed)
    with pytest.warns(UserWarning, match="unnorm_rotations: quaternions were not unit length; normalized"):
        scene = load_scene(d)
    g = scene.gaussians
    assert (g.num_timesteps, g.num_gaussians) == (T, N)
    assert isinstance(g.means, np.memmap) != compressed  # uncompressed members are memory-mapped
    np.testing.assert_array_equal(g.means, p["means3D"])
    np.testing.assert_array_equal(g.colors, p["rgb_colors"])
    q64 = p["unnorm_rotations"].astype(np.float64)
    np.testing.assert_allclose(g.rotations, q64 / np.linalg.norm(q64, axis=-1, keepdims=True), atol=1e-7)
    np.testing.assert_array_equal(g.opacity_logits, p["logit_opacities"][:, 0])
    np.testing.assert_array_equal(g.foreground, np.arange(N) % 2 == 1)
    np.testing.assert_array_equal(np.asarray(scene.metadata["color_correction"]["cam_m"], np.float32), p["cam_m"])
    assert [c.name for c in scene.cameras.cameras(2, "train")] == ["1", "6"]
    assert scene.cameras.num_cameras("test") == 1
    cam = scene.cameras.cameras(1, "train")[1]
    np.testing.assert_allclose(cam.w2c, _meta()["w2c"][1][1])
    assert cam.fx == 51.0 and (cam.width, cam.height) == (64, 36)
    s = scene.summary()
    assert s["num_train_cameras"] == 2 and s["image_size"] == [64, 36] and s["foreground_share"] == 0.5


def test_round_trip_moving_cameras_and_colour_correction(tmp_path):
    g = random_sequence(T, N, sh_degree=None, colors=True, per_frame_scales=True)
    rig = CameraRig(train=[[Camera.from_dict(c, None) for c in
                            [{"K": k, "w2c": w, "width": 64, "height": 36, "name": str(i)}
                             for k, w, i in zip(_meta()["k"][t], _meta()["w2c"][t], (1, 6))]] for t in range(T)],
                    test=[[] for _ in range(T)])
    scene = Scene(g, rig, metadata={"color_correction": {"cam_m": [[0.5, 0.25, 0.0]], "cam_c": [[0, 0, 1.0]]}})
    out = write_dynamic3dgs(scene, tmp_path / "out")
    assert not (out / "test_meta.json").exists()
    back = load_dynamic3dgs(out)
    assert_sequences_equal(back.gaussians, g, rot_atol=2e-7)
    assert_rigs_equal(back.cameras, rig)
    assert back.metadata["color_correction"] == scene.metadata["color_correction"]
    with pytest.raises(OutputExistsError):
        write_dynamic3dgs(scene, tmp_path / "out")
    write_dynamic3dgs(scene, tmp_path / "out", overwrite=True, compressed=True)
    assert_sequences_equal(load_dynamic3dgs(out).gaussians, g, rot_atol=2e-7)
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary leftovers


def test_sh_scene_exports_dc_colour(tmp_path):
    scene = random_scene(T=2, N=5, sh_degree=2)
    back = load_dynamic3dgs(write_dynamic3dgs(scene, tmp_path / "o"))
    for t in range(2):
        np.testing.assert_allclose(back.gaussians.colors[t], 0.5 + 0.28209479177387814 * scene.gaussians.sh[:, 0],
                                   atol=1e-6)
    np.testing.assert_array_equal(back.gaussians.foreground, scene.gaussians.foreground)


def test_without_meta_files_there_are_no_cameras(tmp_path):
    d = tmp_path / "m"
    d.mkdir()
    np.savez(d / "params.npz", **{k: v for k, v in _params().items() if k not in ("seg_colors", "cam_m", "cam_c")})
    scene = load_scene(d / "params.npz")
    assert scene.cameras.num_cameras("train") == 0 and scene.gaussians.foreground is None
    assert "color_correction" not in scene.metadata


@pytest.mark.parametrize("key", ["means3D", "rgb_colors", "unnorm_rotations", "logit_opacities", "log_scales"])
def test_missing_key(tmp_path, key):
    p = _params()
    del p[key]
    with pytest.raises(InputError, match=rf"params\.npz: {key}: missing key \(present: "):
        load_scene(_write(tmp_path, p))


@pytest.mark.parametrize("key,shape,expected", [
    ("rgb_colors", (T, N - 1, 3), r"has shape \(3, 5, 3\), expected \(T=3, N=6, 3\)"),
    ("unnorm_rotations", (T + 1, N, 4), r"has shape \(4, 6, 4\), expected \(T=3, N=6, 4\)"),
    ("unnorm_rotations", (T, N, 3), r"has shape \(3, 6, 3\)"),
    ("logit_opacities", (N + 2, 1), r"has shape \(8, 1\), expected \(N=6, 1\)"),
    ("log_scales", (2, N, 3), r"has shape \(2, 6, 3\), expected \(N=6, 3\) or \(T=3, N=6, 3\)"),
    ("seg_colors", (N, 2), r"has shape \(6, 2\)"),
    ("means3D", (T, N), r"has shape \(3, 6\), expected \(T,N,3\)"),
])
def test_wrong_shape_and_t_or_n_mismatch(tmp_path, key, shape, expected):
    p = _params()
    p[key] = np.ones(shape, np.float32)
    with pytest.raises(InputError, match=rf"params\.npz: {key}: {expected}"):
        load_scene(_write(tmp_path, p))


@pytest.mark.parametrize("dtype", [np.int32, np.bool_, "U3", np.complex64])
def test_wrong_dtype(tmp_path, dtype):
    p = _params()
    p["log_scales"] = np.zeros((N, 3), dtype=dtype)
    with pytest.raises(InputError, match=r"params\.npz: log_scales: has dtype .*, expected a float type"):
        load_scene(_write(tmp_path, p))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_inf(tmp_path, bad):
    p = _params()
    p["means3D"][2, 4, 1] = bad
    with pytest.raises(InputError, match=r"params\.npz: means3D: contains NaN or Inf \(first at index \[2, 4, 1\]\)"):
        load_scene(_write(tmp_path, p))


def test_zero_length_quaternion(tmp_path):
    p = _params()
    p["unnorm_rotations"][1, 3] = 0.0
    with pytest.raises(InputError, match=r"unnorm_rotations: zero-length quaternion at index \[1, 3\]"):
        load_scene(_write(tmp_path, p))


def test_meta_with_wrong_number_of_timesteps(tmp_path):
    with pytest.raises(InputError, match=r"train_meta\.json: k: has 2 timesteps but params\.npz has T=3"):
        load_scene(_write(tmp_path, train=_meta(num_t=2)))


def test_meta_missing_key(tmp_path):
    meta = _meta()
    del meta["w2c"]
    with pytest.raises(InputError, match=r"test_meta\.json: w2c: missing key"):
        load_scene(_write(tmp_path, test=meta))


@pytest.mark.parametrize("focal", [0.0, -10.0])
def test_non_positive_focal(tmp_path, focal):
    meta = _meta()
    meta["k"][1][0][1][1] = focal
    with pytest.raises(InputError, match=r"train_meta\.json: k\[1\]\[0\]: focal length must be positive"):
        load_scene(_write(tmp_path, train=meta))


@pytest.mark.parametrize("kind", ["scaled", "shear", "reflection", "bottom_row"])
def test_non_rigid_w2c(tmp_path, kind):
    meta = _meta()
    w2c = np.array(meta["w2c"][0][1])
    if kind == "scaled":
        w2c[:3, :3] *= 1.1
    elif kind == "shear":
        w2c[0, :3] += 0.2 * w2c[1, :3]
    elif kind == "reflection":
        w2c[0, :] *= -1
    else:
        w2c[3] = [0, 0, 0.1, 1]
    meta["w2c"][0][1] = w2c.tolist()
    with pytest.raises(InputError, match=r"train_meta\.json: w2c\[0\]\[1\]: is not a rigid transform"):
        load_scene(_write(tmp_path, train=meta))


def test_meta_with_nan_and_bad_matrix(tmp_path):
    meta = _meta()
    meta["w2c"][2][0][0][3] = float("nan")
    (tmp_path / "a").mkdir()
    with pytest.raises(InputError, match=r"w2c\[2\]\[0\]: contains NaN or Inf"):
        load_scene(_write(tmp_path / "a", train=meta))
    meta = _meta()
    meta["k"][0][1] = [[1, 0], [0, 1]]
    (tmp_path / "b").mkdir()
    with pytest.raises(InputError, match=r"k\[0\]\[1\]: has shape \(2, 2\), expected \(3, 3\)"):
        load_scene(_write(tmp_path / "b", train=meta))


class _Payload:
    """Unpickling this object creates a marker file: proof that something was unpickled."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_payload_really_fires_when_unpickled(tmp_path):
    marker = tmp_path / "fired"
    pickle.loads(pickle.dumps(_Payload(marker))).close()
    assert marker.exists()  # so the refusal tests below are meaningful


@pytest.mark.parametrize("compressed", [False, True])
def test_object_array_member_is_refused_unexecuted(tmp_path, compressed):
    marker = tmp_path / "fired"
    p = _params()
    p["seg_colors"] = np.array([_Payload(marker)] * N, dtype=object)
    d = _write(tmp_path, p, compressed=compressed)  # np.savez pickles object arrays
    with pytest.raises(InputError, match=r"params\.npz: seg_colors: holds an object/pickled array, which is refused"):
        load_scene(d)
    assert not marker.exists()


def test_pickle_file_posing_as_npz_is_refused_unexecuted(tmp_path):
    marker = tmp_path / "fired"
    d = tmp_path / "p"
    d.mkdir()
    (d / "params.npz").write_bytes(pickle.dumps({"means3D": _Payload(marker)}))
    with pytest.raises(InputError, match=r"params\.npz: is a Python pickle, not an \.npz archive"):
        load_scene(d)
    assert not marker.exists()


@pytest.mark.parametrize("cut", [0.5, 0.98])
def test_truncated_archive(tmp_path, cut):
    d = _write(tmp_path)
    data = (d / "params.npz").read_bytes()
    (d / "params.npz").write_bytes(data[:int(len(data) * cut)])
    with pytest.raises(InputError, match=r"params\.npz: corrupt or truncated \.npz archive"):
        load_scene(d)


def test_corrupt_member_header(tmp_path):
    d = _write(tmp_path)
    data = bytearray((d / "params.npz").read_bytes())
    i = data.index(b"\x93NUMPY")  # break the first member's .npy magic
    data[i:i + 6] = b"garbag"
    (d / "params.npz").write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"params\.npz: \w+: corrupt"):
        load_scene(d)


def test_timestep_out_of_range(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load_scene(_write(tmp_path))
    assert scene.gaussians.at(T - 1).means.shape == (N, 3)
    for t in (T, -1):
        with pytest.raises(InputError, match=rf"params\.npz: t: timestep {t} is out of range 0\.\.2"):
            scene.gaussians.at(t)
    with pytest.raises(InputError, match=r"timestep 3 is out of range"):
        scene.cameras.cameras(3)
