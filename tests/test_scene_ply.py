"""3DGS PLY reader/writer: round trips, the Inria layout by hand, and every bad-input case."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.scene import load_scene
from fourlegs_engine.scene.gaussians import SH_C0
from fourlegs_engine.scene.ply import (natural_key, read_ply_splats, write_ply_scene, write_ply_splats)

from _scene_helpers import assert_sequences_equal, random_scene, random_unit_quaternions

ENCODINGS = ("binary_little_endian", "binary_big_endian", "ascii")


def _splats(N=7, degree=2, seed=0):
    rng = np.random.default_rng(seed)
    return dict(means=rng.normal(size=(N, 3)).astype(np.float32),
                rotations=random_unit_quaternions(rng, (N,)),
                log_scales=rng.normal(-3, 1, size=(N, 3)).astype(np.float32),
                opacity_logits=rng.normal(size=N).astype(np.float32),
                sh=rng.normal(size=(N, (degree + 1) ** 2, 3)).astype(np.float32))


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_every_encoding_and_degree(tmp_path, encoding, degree):
    data = _splats(degree=degree, seed=degree)
    normals = np.zeros((7, 3), np.float32) if degree % 2 else None
    path = write_ply_splats(tmp_path / "g.ply", **data, normals=normals, encoding=encoding)
    assert path.read_bytes().split(b"\n")[1] == f"format {encoding} 1.0".encode()
    back = read_ply_splats(path)
    for key in ("means", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, key), data[key], err_msg=key)
    np.testing.assert_allclose(back.rotations, data["rotations"], rtol=0, atol=2e-7)
    assert back.sh_degree == degree
    assert (back.normals is None) == (normals is None)


def _write_text(path, properties, rows, fmt="ascii"):
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(rows)}"]
    header += [p if p.startswith("property list") else f"property float {p}" for p in properties]
    header += ["end_header"]
    body = "\n".join(" ".join(str(v) for v in r) for r in rows)
    path.write_text("\n".join(header) + "\n" + body + "\n")
    return path


INRIA_DEG1 = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
              + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def test_hand_written_inria_file_maps_channel_major_sh(tmp_path):
    # f_rest_i = 10*channel + coefficient: channel-major means i = channel*3 + (coefficient-1)
    f_rest = [10 * c + k for c in range(3) for k in range(1, 4)]
    row = [1, 2, 3, 0, 0, 0, 0.5, -0.5, 1.0] + f_rest + [0.25, -1, -2, -3, 2, 0, 0, 0]
    with pytest.warns(UserWarning, match="normalized"):
        s = read_ply_splats(_write_text(tmp_path / "inria.ply", INRIA_DEG1, [row]))
    np.testing.assert_array_equal(s.means, [[1, 2, 3]])
    expected_sh = np.array([[[0.5, -0.5, 1.0], [1, 11, 21], [2, 12, 22], [3, 13, 23]]], np.float32)
    np.testing.assert_array_equal(s.sh, expected_sh)
    np.testing.assert_array_equal(s.rotations, [[1, 0, 0, 0]])  # (2,0,0,0) normalized
    np.testing.assert_array_equal(s.log_scales, [[-1, -2, -3]])
    np.testing.assert_array_equal(s.opacity_logits, [0.25])
    with pytest.warns(UserWarning, match="normalized"):
        scene = load_scene(tmp_path / "inria.ply")
    np.testing.assert_allclose(scene.gaussians.rgb(0), [[0.5 + SH_C0 * 0.5, 0.5 - SH_C0 * 0.5, 0.5 + SH_C0]])


def test_big_endian_bytes_are_decoded(tmp_path):
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    values = np.array([1.5, -2.0, 3.25, 0, 0, 0, 0.1, -1, -1, -1, 0, 0, 0, 1], dtype=">f4")
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 1\n" + "".join(
        f"property float {p}\n" for p in props) + "end_header\n"
    (tmp_path / "be.ply").write_bytes(header.encode() + values.tobytes())
    s = read_ply_splats(tmp_path / "be.ply")
    np.testing.assert_array_equal(s.means, [[1.5, -2.0, 3.25]])
    np.testing.assert_array_equal(s.rotations, [[0, 0, 0, 1]])


def test_directory_sequence_natural_order_and_scene_round_trip(tmp_path):
    scene = random_scene(T=3, N=20, sh_degree=3)
    out = write_ply_scene(scene, tmp_path / "seq", encoding="binary_big_endian")
    for t, old in enumerate(sorted(out.iterdir())):  # rename to names that sort wrongly as strings
        old.rename(out / f"f_{[1, 2, 10][t]}.ply")
    back = load_scene(out)
    assert back.num_timesteps == 3 and back.metadata["frames"] == ["f_1.ply", "f_2.ply", "f_10.ply"]
    assert_sequences_equal(back.gaussians, _without(scene.gaussians, "colors", "foreground"), rot_atol=2e-7)
    assert sorted(["f_10.ply", "f_2.ply", "f_1.ply"], key=lambda n: natural_key(out / n)) == \
        ["f_1.ply", "f_2.ply", "f_10.ply"]


def _without(g, *names):
    import dataclasses
    return dataclasses.replace(g, **{n: None for n in names})


def test_colour_only_scene_exports_as_degree_zero(tmp_path):
    scene = random_scene(T=1, N=10, sh_degree=None, colors=True)
    write_ply_scene(scene, tmp_path / "one.ply")
    back = load_scene(tmp_path / "one.ply")
    assert back.gaussians.sh.shape == (10, 1, 3)
    np.testing.assert_allclose(back.gaussians.rgb(0), scene.gaussians.colors[0], atol=1e-6)
    with pytest.raises(OutputExistsError):
        write_ply_scene(scene, tmp_path / "one.ply")


def test_many_timesteps_into_one_file_is_refused(tmp_path):
    with pytest.raises(InputError, match="one PLY file holds one timestep"):
        write_ply_scene(random_scene(T=2, N=5), tmp_path / "x.ply")


def test_frames_with_different_n_name_the_file(tmp_path):
    write_ply_splats(tmp_path / "frame_0.ply", **_splats(N=7))
    write_ply_splats(tmp_path / "frame_1.ply", **_splats(N=6))
    with pytest.raises(InputError, match=r"frame_1\.ply: vertex: has 6 Gaussians but frame_0\.ply has 7"):
        load_scene(tmp_path)


def test_frames_with_different_sh_degree(tmp_path):
    write_ply_splats(tmp_path / "a0.ply", **_splats(degree=1))
    write_ply_splats(tmp_path / "a1.ply", **_splats(degree=2))
    with pytest.raises(InputError, match=r"a1\.ply: f_rest: has SH degree 2 but a0\.ply has degree 1"):
        load_scene(tmp_path)


def test_point_cloud_is_not_splats(tmp_path):
    path = tmp_path / "cloud.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                    "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                    "end_header\n0 0 0 255 0 0\n1 1 1 0 255 0\n")
    with pytest.raises(InputError) as err:
        load_scene(path)
    msg = str(err.value)
    assert msg.startswith(str(path)) and "point cloud, not Gaussian splats" in msg
    for prop in ("opacity", "scale_0", "rot_3"):
        assert prop in msg


def test_missing_single_property_is_named(tmp_path):
    props = [p for p in INRIA_DEG1 if p != "rot_3"]
    row = [0.0] * len(props)
    row[props.index("rot_0")] = 1.0
    with pytest.raises(InputError, match=r"vertex: missing Gaussian splat properties \['rot_3'\]"):
        read_ply_splats(_write_text(tmp_path / "m.ply", props, [row]))


def test_wrong_number_of_sh_coefficients(tmp_path):
    props = [p for p in INRIA_DEG1 if p != "f_rest_8"]
    row = [0.0] * len(props)
    row[props.index("rot_0")] = 1.0
    with pytest.raises(InputError, match="f_rest: has 8 f_rest coefficients; expected 0, 9, 24 or 45"):
        read_ply_splats(_write_text(tmp_path / "m.ply", props, [row]))


def test_list_property_has_wrong_type(tmp_path):
    props = [p if p != "opacity" else "property list uchar float opacity" for p in INRIA_DEG1]
    row = ["1 0.5" if p == "opacity" else ("1" if p == "rot_0" else "0") for p in INRIA_DEG1]
    with pytest.raises(InputError, match="opacity: is a list property"):
        read_ply_splats(_write_text(tmp_path / "l.ply", props, [row]))


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_nan_and_inf_are_named(tmp_path, bad):
    row = ["0"] * len(INRIA_DEG1)
    row[INRIA_DEG1.index("rot_0")] = "1"
    row[INRIA_DEG1.index("scale_1")] = bad
    rows = [["0"] * len(INRIA_DEG1), row]
    rows[0][INRIA_DEG1.index("rot_0")] = "1"
    with pytest.raises(InputError, match=r"n\.ply: scale_1: contains NaN or Inf \(first at vertex 1\)"):
        read_ply_splats(_write_text(tmp_path / "n.ply", INRIA_DEG1, rows))


def test_zero_length_quaternion(tmp_path):
    data = _splats(N=4)
    data["rotations"][2] = 0
    write_ply_splats(tmp_path / "z.ply", **data)
    with pytest.raises(InputError, match=r"z\.ply: rot_0\.\.3: zero-length quaternion at index \[2\]"):
        read_ply_splats(tmp_path / "z.ply")


def test_unnormalized_quaternions_are_fixed_with_a_warning(tmp_path):
    data = _splats(N=4)
    data["rotations"] = data["rotations"] * np.float32(3.0)
    write_ply_splats(tmp_path / "u.ply", **data)
    with pytest.warns(UserWarning, match="not unit length; normalized"):
        s = read_ply_splats(tmp_path / "u.ply")
    np.testing.assert_allclose(np.linalg.norm(s.rotations, axis=1), 1.0, atol=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # unit quaternions: no warning
        write_ply_splats(tmp_path / "ok.ply", **_splats(N=4))
        read_ply_splats(tmp_path / "ok.ply")


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_truncated_file(tmp_path, encoding):
    path = write_ply_splats(tmp_path / "t.ply", **_splats(N=5), encoding=encoding)
    data = path.read_bytes()
    # binary: any cut is detected; ASCII: a cut inside the last number is indistinguishable from a
    # shorter number, so cut past it (the last row then misses values)
    path.write_bytes(data[:-9] if encoding != "ascii" else data[:-40])
    with pytest.raises(InputError, match=r"t\.ply: corrupt or truncated PLY file"):
        read_ply_splats(path)


@pytest.mark.parametrize("content", [b"", b"not a ply file at all\n", b"ply\nformat binary_little_endian 1.0\n",
                                     b"\x89PNG\r\n\x1a\n\x00\x00"])
def test_corrupt_header(tmp_path, content):
    (tmp_path / "c.ply").write_bytes(content)
    with pytest.raises(InputError, match=r"c\.ply: corrupt or truncated PLY file"):
        load_scene(tmp_path / "c.ply")


def test_ascii_with_a_word_instead_of_a_number(tmp_path):
    row = ["0"] * len(INRIA_DEG1)
    row[3] = "abc"
    with pytest.raises(InputError, match="corrupt or truncated PLY file"):
        read_ply_splats(_write_text(tmp_path / "w.ply", INRIA_DEG1, [row]))


def test_no_vertex_element_and_empty(tmp_path):
    (tmp_path / "f.ply").write_text("ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
                                    "end_header\n")
    with pytest.raises(InputError, match="has no 'vertex' element"):
        read_ply_splats(tmp_path / "f.ply")
    write_ply_splats(tmp_path / "e.ply", **_splats(N=0))
    with pytest.raises(InputError, match=r"e\.ply: vertex: has no vertices"):
        read_ply_splats(tmp_path / "e.ply")


def test_static_scene_timestep_out_of_range(tmp_path):
    write_ply_splats(tmp_path / "s.ply", **_splats())
    g = load_scene(tmp_path / "s.ply").gaussians
    assert g.at(0).means.shape == (7, 3)
    with pytest.raises(InputError, match=r"s\.ply: t: timestep 1 is out of range 0\.\.0"):
        g.at(1)


def test_inria_model_directory_with_cameras_json(tmp_path):
    model = tmp_path / "garden"
    for it, n in ((7000, 5), (30000, 7)):
        write_ply_splats(model / "point_cloud" / f"iteration_{it}" / "point_cloud.ply", **_splats(N=n))
    # columns = camera axes in world: x right = +x, y down = -z, z forward = +y (looks at the origin)
    c2w_rot = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)
    (model / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "DSC001", "width": 80, "height": 60,
                                                     "position": [0, -5, 0], "rotation": c2w_rot.tolist(),
                                                     "fx": 70.0, "fy": 70.0}]))
    scene = load_scene(model)
    assert scene.num_gaussians == 7 and scene.name == "garden"
    cam = scene.cameras.find("DSC001")
    np.testing.assert_allclose(cam.center, [0, -5, 0])
    np.testing.assert_allclose(cam.c2w[:3, :3], c2w_rot)
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0]]))  # the origin: straight ahead, 5 m away
    np.testing.assert_allclose(z, [5.0])
    np.testing.assert_allclose(uv, [[40, 30]])


@settings(max_examples=15)
@given(values=hnp.arrays(np.float32, (3, 19), elements=st.floats(width=32, allow_nan=False, allow_infinity=False)),
       encoding=st.sampled_from(ENCODINGS))
def test_extreme_float32_values_survive_every_encoding(tmp_path_factory, values, encoding):
    """Subnormals, -0.0 and float32 max must come back bit-exact (ASCII included)."""
    N = values.shape[0]
    q = np.tile(np.float32([1, 0, 0, 0]), (N, 1))
    path = tmp_path_factory.mktemp("x") / "v.ply"
    sh = values[:, 7:19].reshape(N, 4, 3)
    write_ply_splats(path, values[:, 0:3], q, values[:, 3:6], values[:, 6], sh, encoding=encoding)
    s = read_ply_splats(path)
    for got, want in ((s.means, values[:, 0:3]), (s.log_scales, values[:, 3:6]), (s.opacity_logits, values[:, 6]),
                      (s.sh, sh)):
        np.testing.assert_array_equal(got.view(np.uint32), np.ascontiguousarray(want).view(np.uint32))


def test_double_and_integer_properties_are_converted(tmp_path):
    import plyfile

    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    table = np.zeros(2, dtype=[(n, "<f8" if n in "xyz" else ("<i4" if n.startswith("rot") else "<f4"))
                               for n in names])
    table["x"] = [0.1, 1e-40]  # 1e-40 is a float32 subnormal
    table["rot_0"] = [1, 3]
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(tmp_path / "d.ply"))
    with pytest.warns(UserWarning, match="normalized"):
        s = read_ply_splats(tmp_path / "d.ply")
    assert s.means.dtype == np.float32 and s.means[0, 0] == np.float32(0.1) and s.means[1, 0] == np.float32(1e-40)
    np.testing.assert_array_equal(s.rotations, [[1, 0, 0, 0], [1, 0, 0, 0]])
    table["y"][1] = 1e300  # finite as a double, infinite as float32
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(tmp_path / "big.ply"))
    with pytest.raises(InputError, match=r"big\.ply: y: contains a value too large for float32 \(1e\+300\) "
                                         r"\(first at vertex 1\)"):
        read_ply_splats(tmp_path / "big.ply")
