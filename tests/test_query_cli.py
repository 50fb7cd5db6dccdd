"""``fourlegs query`` end to end on a small bundle; EXR and plot outputs; multi-scene ranking."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fourlegs_engine.commands.main import main
from fourlegs_engine import pipeline
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.exr import read_exr, write_exr
from fourlegs_engine.query.multiscene import rank_scenes
from fourlegs_engine.query.plots import plot_temporal
from fourlegs_engine.query.temporal import localize_relevancy
from fourlegs_engine.scene.bundle import write_bundle

from _query_helpers import two_cluster_scene


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A bundle with a real decoder file whose first layers pass the latent through unchanged."""
    return _clusters_bundle(tmp_path_factory.mktemp("q") / "clusters", active=(2, 3))


def _clusters_bundle(root, active, T=5):
    from fourlegs_engine.language.autoencoder import FeatureDecoder

    scene, field, enc, dirs = two_cluster_scene(T=T, active=active, d=8, D=16)
    scene.gaussians.latents = field.latents
    write_bundle(scene, root)
    dec = FeatureDecoder((8, 8, 8, 16))
    with torch.no_grad():
        for m in dec.modules():
            if isinstance(m, torch.nn.Linear):
                m.weight.zero_()
                m.bias.zero_()
        lin = [m for m in dec.modules() if isinstance(m, torch.nn.Linear)]
        lin[0].weight.copy_(torch.eye(8))
        lin[1].weight.copy_(torch.eye(8))
        lin[2].weight.copy_(field.weight.T.clone())
    torch.save(dec.state_dict(), root / "language" / "decoder.pt")
    from fourlegs_engine.scene.bundle import update_bundle_meta
    update_bundle_meta(root, language={"encoder": "table", "latent_dim": 8, "latents": "language/latents.npy",
                                       "decoder": "language/decoder.pt",
                                       "canonical_phrases": ["object", "things", "stuff", "texture"]})
    return root, enc


def field_weight_rows(root):
    _, field, _, _ = two_cluster_scene(T=5, active=(2, 3), d=8, D=16)
    w = field.weight.numpy()[[0, 4]]
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def test_query_command_writes_json_plot_and_exr(bundle, tmp_path, monkeypatch, capsys):
    root, enc = bundle
    monkeypatch.setattr(pipeline, "text_encoder", lambda scene, config=None: enc)
    from fourlegs_engine.language.field import LanguageField
    field = LanguageField.open(root)
    # the stored decoder reproduces the test's linear map (BatchNorm at its initial statistics)
    expect = field_weight_rows(root)
    np.testing.assert_allclose(field.decode(torch.eye(8)[[0, 4]]).numpy(), expect, atol=1e-3)
    out = tmp_path / "out.json"
    rc = main(["query", str(root), "a ball flying", "--json", str(out), "--exr", str(tmp_path / "maps"),
               "--spatial", "fast", "--frames", "peak", "2", "4"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "s_t |" in text and "segment" in text
    data = json.loads(out.read_text())
    assert data["found"] and data["segment"][0] <= 2 <= data["segment"][1]
    assert (tmp_path / "out.st.png").read_bytes()[:4] == b"\x89PNG"
    assert len(data["exr"]) == 2
    maps = read_exr(data["exr"][0])
    assert set(maps) == {"relevancy", "depth", "alpha"} and maps["alpha"].max() > 0.5
    # existing output is not overwritten without --overwrite; a bad frame is one clear error
    assert main(["query", str(root), "a ball flying", "--json", str(out)]) == 2
    assert main(["query", str(root), "a ball flying", "--exr", str(tmp_path / "m2"), "--frames", "x"]) == 2
    assert main(["query", str(tmp_path / "nope"), "a ball flying"]) == 2
    assert main(["query", str(root), "  "]) == 2
    assert "error" in capsys.readouterr().err


def test_exr_roundtrip_and_bad_channels(tmp_path):
    rel = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    depth = np.full((3, 4), np.nan, np.float32)
    write_exr(tmp_path / "a.exr", {"relevancy": rel, "depth": depth})
    back = read_exr(tmp_path / "a.exr")
    np.testing.assert_array_equal(back["relevancy"], rel)
    assert np.all(back["depth"] == 0)
    from fourlegs_engine.errors import InputError, OutputExistsError
    with pytest.raises(OutputExistsError):
        write_exr(tmp_path / "a.exr", {"relevancy": rel})
    with pytest.raises(InputError):
        write_exr(tmp_path / "b.exr", {"relevancy": rel, "depth": np.zeros((2, 2))})
    assert not (tmp_path / "b.exr").exists()


def test_plot_found_and_not_found(tmp_path):
    R = np.full((8, 5), 0.2)
    R[3:5] = 0.9
    p = plot_temporal(localize_relevancy(R), tmp_path / "a.png", query="q")
    assert p.read_bytes()[:4] == b"\x89PNG"
    plot_temporal(localize_relevancy(np.zeros((8, 5))), tmp_path / "b.png")
    assert (tmp_path / "b.png").stat().st_size > 0


def test_multiscene_ranks_the_scene_with_the_action_first():
    with_ball = two_cluster_scene(T=20, active=range(5, 9), seed=0)
    without = two_cluster_scene(T=20, active=(), seed=0)
    enc = with_ball[2]
    engines = {"without": QueryEngine(without[0], without[1], enc, QueryOptions.exact()),
               "with": QueryEngine(with_ball[0], with_ball[1], enc, QueryOptions.exact())}
    res = rank_scenes(engines, "a ball flying", stride=2)
    assert res.best == "with" and res.ranking[0][0] == "with" and res.ranking[1][1] == 0.0
    assert res.localization.temporal.found and engines["without"].stats["temporal"] == 1
    json.dumps(res.to_dict(), allow_nan=False)
    assert rank_scenes({"without": engines["without"]}, "a ball flying").best is None


def test_query_with_several_scenes_ranks_them_and_localizes_in_the_best(bundle, tmp_path, monkeypatch, capsys):
    from fourlegs_engine.language.field import LanguageField
    from fourlegs_engine.query.multiscene import scene_relevance
    from fourlegs_engine.query.options import QueryOptions
    from fourlegs_engine.scene.bundle import load_bundle

    root, enc = bundle
    without, _ = _clusters_bundle(tmp_path / "quiet", active=())
    late, _ = _clusters_bundle(tmp_path / "late", active=(9, 10, 11), T=20)
    monkeypatch.setattr(pipeline, "text_encoder", lambda scene, config=None: enc)
    paths = (without, late, root)

    def expected(stride):  # max_t s_t on every stride-th timestep, computed here scene by scene
        out = {}
        for path in paths:
            engine = QueryEngine(load_bundle(path), LanguageField.open(path), enc, QueryOptions.exact())
            out[str(path)] = scene_relevance(engine, "a ball flying", stride)
        return out

    for stride, best in ((10, late), (1, root)):  # at stride 10 the short scene's action is not sampled
        out = tmp_path / f"rank{stride}.json"
        extra = [] if stride == 10 else ["--scene-stride", str(stride)]
        rc = main(["query", *map(str, paths), "a ball flying", "--json", str(out), "--no-spatial", *extra])
        text = capsys.readouterr().out
        assert rc == 0, text
        data = json.loads(out.read_text())
        want = expected(stride)
        names = [n for n, _ in data["ranking"]]
        assert {n: s for n, s in data["ranking"]} == pytest.approx(want)
        assert names == sorted(want, key=lambda n: -want[n]) and want[str(without)] == 0.0
        assert data["best"] == names[0] == str(best) and data["scene_stride"] == stride
        assert data["localization"]["found"] and want[str(best)] > max(v for k, v in want.items() if k != str(best))
        table = [line.split() for line in text.splitlines() if line.split()[:1] in (["1"], ["2"], ["3"])]
        assert [row[1] for row in table] == names and table[0][-1] == "best"
    # ranking only: exr/plot of one scene are refused, as is a scene given twice
    assert main(["query", str(root), str(late), "a ball flying", "--exr", str(tmp_path / "m")]) == 2
    assert main(["query", str(root), str(root), "a ball flying"]) == 2
    assert main(["query", str(root), "a ball flying", "--scene-stride", "2"]) == 2
    assert not (tmp_path / "m").exists()
