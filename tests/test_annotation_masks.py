"""The annotation-mask encoder (``--encoder masks``): features from per-pixel masks, lifted and queried."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from _language_helpers import micro_bundle
from fourlegs_bench.metrics import average_precision
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError
from fourlegs_engine.language.autoencoder import AETrainOptions, train_autoencoder
from fourlegs_engine.language.distill import distill_scene
from fourlegs_engine.language.annotations import AnnotationMaskEncoder, mask_pairs, phrase_embedding
from fourlegs_engine.language.encoders import CANONICAL_PHRASES, get_encoder
from fourlegs_engine.language.extract import extract_features, feature_store
from fourlegs_engine.language.coverage import render_label_coverage
from fourlegs_engine.pipeline import EncoderOptions, open_query_engine, text_encoder
from fourlegs_engine.scene.bundle import load_bundle

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "panoptic-basketball"


def write_masks(folder: Path, masks: dict[tuple[str, int], np.ndarray]) -> Path:
    for (cam, t), mask in masks.items():
        (folder / cam).mkdir(parents=True, exist_ok=True)
        Image.fromarray(mask.astype(np.uint8) * 255).save(folder / cam / f"{t:06d}.png")
    return folder


def person_masks(scene, folder: Path) -> dict[tuple[str, int], np.ndarray]:
    """The micro scene's 'person jumping' pixels (label coverage > 0.5) as hand-made annotation masks."""
    masks = {}
    for t in range(scene.num_timesteps):
        for cam in scene.cameras.cameras(t, "train") + scene.cameras.cameras(t, "test"):
            masks[(cam.name, t)] = render_label_coverage(scene, cam, t)[1].numpy() > 0.5
    write_masks(folder, masks)
    return masks


def test_phrase_embeddings_are_deterministic_unit_and_separate():
    e = AnnotationMaskEncoder()
    a, b = e.encode_text(["a person", "A  Person"]), e.encode_text(["a car"])
    assert torch.allclose(a[0], a[1]) and torch.allclose(a.norm(dim=1), torch.ones(2))
    assert abs(float(a[0] @ b[0]) - 0.3) < 0.05  # only the shared generic share
    canon = e.encode_text(list(CANONICAL_PHRASES))
    assert float((canon @ a[0]).max()) < float(a[0] @ a[0]) - 0.4


def test_coverage_features_equal_the_phrase_embedding_where_set(tmp_path):
    enc = AnnotationMaskEncoder({"a person": tmp_path, "a ball": tmp_path / "b"})
    full = torch.tensor([[[1.0, 0.0]] * 8, [[0.0, 1.0]] * 8, [[0.0, 0.0]] * 8])        # (3, 8, 2)
    out = enc.encode_coverage(full).double()
    assert torch.allclose(out[0], torch.from_numpy(phrase_embedding("a person")), atol=1e-6)
    assert torch.allclose(out[1], torch.from_numpy(phrase_embedding("a ball")), atol=1e-6)
    assert torch.allclose(out[2], torch.from_numpy(phrase_embedding("background")), atol=1e-6)


PHRASES = ["the ball", "the ball in the air", "a person holding the ball", "a person", "a dog", "the net",
           "a referee", "the hoop"]


def _relevancy_of_each(features: torch.Tensor, phrases: list[str]) -> np.ndarray:
    """(B, P) LERF relevancy of each phrase, float64."""
    from fourlegs_engine.query.lerf import relevancy
    canon = torch.from_numpy(np.stack([phrase_embedding(c) for c in CANONICAL_PHRASES]))
    return np.stack([relevancy(features.double(), torch.from_numpy(phrase_embedding(p)), canon).numpy()
                     for p in phrases], axis=1)


@settings(max_examples=20, deadline=None)
@given(st.sets(st.integers(0, len(PHRASES) - 1), min_size=1, max_size=5), st.floats(0.5, 1.0))
def test_a_crop_in_overlapping_masks_is_relevant_to_each_of_them_and_to_no_other(covered, share):
    """The ball inside 'a person holding the ball' inside 'a person': each covering phrase scores above
    0.5 and every other phrase below, for up to five overlapping phrases (each covering ``share`` of the
    crop, the rest background)."""
    enc = AnnotationMaskEncoder({p: f"/nonexistent/{i}" for i, p in enumerate(PHRASES)})
    cov = torch.zeros(1, 8, len(PHRASES), dtype=torch.float64)
    for k in covered:
        cov[0, :, k] = share
    rel = _relevancy_of_each(enc.encode_coverage(cov), PHRASES)[0]
    inside = np.array([k in covered for k in range(len(PHRASES))])
    assert rel[inside].min() > 0.5 and rel[~inside].max() < 0.5, (sorted(covered), share, rel.round(3))


def test_a_plain_weighted_sum_would_lose_overlapping_phrases():
    """The failure the mix rule fixes: with the weighted sum of the embeddings, a crop inside the masks of
    'the ball', 'the ball in the air' and 'a person' is below 0.5 for all three (the generic shares add
    up); the rule keeps all three above 0.5."""
    phrases = ["the ball", "the ball in the air", "a person"]
    emb = torch.from_numpy(np.stack([phrase_embedding(p) for p in phrases]))
    plain = emb.sum(dim=0, keepdim=True)
    assert _relevancy_of_each(plain, phrases).max() < 0.5
    enc = AnnotationMaskEncoder({p: f"/nonexistent/{i}" for i, p in enumerate(phrases)})
    mixed = enc.encode_coverage(torch.ones(1, 8, 3, dtype=torch.float64))
    assert _relevancy_of_each(mixed, phrases).min() > 0.75


@settings(max_examples=15, deadline=None)
@given(st.lists(st.floats(0.0, 1e6, allow_subnormal=False), min_size=3, max_size=3), st.integers(0, 2 ** 31 - 1))
def test_mix_embeddings_matches_a_float64_reference(weights, seed):
    from fourlegs_engine.language.annotations import mix_embeddings
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=16)
    axis /= np.linalg.norm(axis)
    emb = rng.normal(size=(3, 16))
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum() if w.sum() > 0 else np.full(3, 1 / 3)
    g = emb @ axis
    spec = emb - g[:, None] * axis
    direction = w @ spec
    ref = (w @ g) * axis + (w @ np.linalg.norm(spec, axis=1)) * direction / np.linalg.norm(direction)
    ref /= np.linalg.norm(ref)
    out = mix_embeddings(torch.tensor([weights], dtype=torch.float64), torch.from_numpy(emb),
                         torch.from_numpy(axis))[0].numpy()
    assert np.isfinite(out).all() and abs(np.linalg.norm(out) - 1) < 1e-12
    np.testing.assert_allclose(out, ref, atol=1e-10)
    # one embedding holding all the weight comes back unchanged
    single = mix_embeddings(torch.tensor([[0.0, 7.0, 0.0]], dtype=torch.float64), torch.from_numpy(emb),
                            torch.from_numpy(axis))[0].numpy()
    np.testing.assert_allclose(single, emb[1], atol=1e-12)


def test_masks_lift_to_the_masked_region(tmp_path):
    bundle = micro_bundle(tmp_path / "scene", T=2)
    scene = load_bundle(bundle)
    masks = person_masks(scene, tmp_path / "masks")
    config = EncoderOptions(name="masks", masks=(("a person", str(tmp_path / "masks")),))
    encoder = text_encoder(scene, config)
    extract_features(scene, encoder)
    assert feature_store(scene).config["frames"] == "annotation-masks"
    train_autoencoder(scene, AETrainOptions(epochs=1, samples=1024, heldout_samples=128, batch_size=256))
    distill_scene(scene, mode="lift")
    scene = load_bundle(bundle)
    assert scene.language["encoder"] == "masks"
    assert scene.language["encoder_config"]["masks"] == {"a person": str((tmp_path / "masks").resolve())}
    engine = open_query_engine(scene)  # "auto" reopens the recorded encoder
    assert engine.text_encoder.name == "masks"
    cam = scene.cameras.cameras(0, "test")[0]  # never lifted from
    person = np.asarray(scene.gaussians.labels[0]) == 1
    for t in (0, 1):
        rel = engine.relevancy_map("a person", cam, t, outputs=("relevancy",))["relevancy"]
        gt = masks[(cam.name, t)]
        assert gt.any() and average_precision(rel.ravel(), gt.ravel()) > 0.8
        assert rel[gt].mean() > rel[~gt].mean()
        per_gaussian = np.asarray(engine.gaussian_relevancy("a person", t))
        assert average_precision(per_gaussian, person) > 0.8


def test_bad_inputs_give_one_clear_error(tmp_path):
    bundle = micro_bundle(tmp_path / "scene", T=2)
    scene = load_bundle(bundle)
    cams = scene.cameras.cameras(0, "train")
    with pytest.raises(InputError, match="mask folder of 'a person' does not exist"):
        extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "nowhere"}))
    empty = write_masks(tmp_path / "empty", {(c.name, t): np.zeros((18, 32), bool) for c in cams for t in range(2)})
    with pytest.raises(InputError, match="every mask of 'a person' is empty"):
        extract_features(scene, AnnotationMaskEncoder({"a person": empty}))
    small = write_masks(tmp_path / "small", {(c.name, t): np.ones((9, 16), bool) for c in cams for t in range(2)})
    with pytest.raises(InputError, match="mask is 16x9, camera 'cam00' images are 32x18"):
        extract_features(scene, AnnotationMaskEncoder({"a person": small}))
    (tmp_path / "none" / cams[0].name).mkdir(parents=True)
    (tmp_path / "none" / cams[0].name / "notes.txt").write_text("no masks here")
    with pytest.raises(InputError, match=r"no mask of 'a person' for any of the 3 training cameras at timesteps 0\.\.1"):
        extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "none"}))
    # two phrases annotated in disjoint views: no view is labelled for both, so none may vote
    first = write_masks(tmp_path / "first", {(cams[0].name, t): np.ones((18, 32), bool) for t in range(2)})
    second = write_masks(tmp_path / "second", {(cams[1].name, t): np.ones((18, 32), bool) for t in range(2)})
    with pytest.raises(InputError, match="no camera-timestep has the masks of every phrase .'a person': 2, 'a ball': 2"):
        extract_features(scene, AnnotationMaskEncoder({"a person": first, "a ball": second}))
    for spec in ("a person", "=folder", "a person=", ["a=x", "A =y"]):
        with pytest.raises(InputError, match="--masks"):
            mask_pairs([spec] if isinstance(spec, str) else spec)
    with pytest.raises(InputError, match="unknown option"):
        get_encoder("masks", colour="red")
    assert not (Path(bundle) / "features" / "t000000.npy").exists()


def test_cli_bad_spec_and_missing_folder_are_one_line(tmp_path, capsys):
    bundle = micro_bundle(tmp_path / "scene", T=2)
    assert main(["language", str(bundle), "--encoder", "masks", "--masks", "no equals sign"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--masks" in err[0] and "PHRASE=FOLDER" in err[0]
    assert main(["language", str(bundle), "--no-progress", "--encoder", "masks", "--masks",
                 f"a person={tmp_path / 'missing'}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0] and "missing" in err[0]


@pytest.mark.skipif(not (REAL / "seg").is_dir(), reason=f"shared real data absent ({REAL})")
def test_real_masks_extract_on_real_cameras(tmp_path):
    """Three real basketball cameras (640x360, their calibration), two timesteps, the capture's seg/ masks:
    the features are finite, crops inside a person are the phrase's embedding, crops away from people the
    background's. (Full resolution: masks at another size are refused by design. The lift on the fitted
    real scene is measured by `fourlegs bench real-lift`.)"""
    from _language_helpers import micro_scene
    from fourlegs_engine.scene.bundle import write_bundle
    from fourlegs_engine.scene.camera import CameraRig
    from fourlegs_engine.scene.dynamic3dgs import read_meta
    from fourlegs_engine.scene.scene import Scene

    start = time.perf_counter()
    cams = read_meta(REAL / "train_meta.json", 150)[0][:3]
    micro = micro_scene(T=2)
    scene = load_bundle(write_bundle(Scene(gaussians=micro.gaussians, cameras=CameraRig.static(cams, [], 2),
                                           name="real-cams"), tmp_path / "scene"))
    enc = AnnotationMaskEncoder({"a person": REAL / "seg"})
    extract_features(scene, enc)
    store = feature_store(scene)
    feats = np.stack([store.load(t) for t in range(2)]).astype(np.float64)        # (2, crops, 768)
    assert np.isfinite(feats).all()
    cos_person = feats @ phrase_embedding("a person")
    cos_background = feats @ phrase_embedding("background")
    assert cos_person.max() > 0.95 and cos_background.max() > 0.99
    assert (cos_background > 0.99).mean() > 0.3  # people fill a small part of each view
    assert time.perf_counter() - start < 60


def test_views_without_masks_give_no_evidence_and_do_not_vote(tmp_path, capsys):
    """Masks for two of the three training cameras: the third camera's feature rows are zero, and the field
    lifted from the full rig equals the one lifted from a rig of the two annotated cameras only."""
    from fourlegs_engine.language.autoencoder import ENCODER_FILE, load_encoder
    from fourlegs_engine.language.distill import DistillOptions, distill_timestep
    from fourlegs_engine.language.extract import camera_layouts
    from fourlegs_engine.scene.bundle import write_bundle
    from fourlegs_engine.scene.camera import CameraRig
    from fourlegs_engine.scene.scene import Scene

    full = load_bundle(micro_bundle(tmp_path / "full", T=2))
    masks = person_masks(full, tmp_path / "masks")
    cams = full.cameras.cameras(0, "train")
    import shutil
    shutil.rmtree(tmp_path / "masks" / cams[1].name)       # camera 1 never annotated
    (tmp_path / "masks" / cams[2].name / "000001.png").unlink()  # camera 2 annotated at t=0 only
    assert main(["language", str(full.root), "--no-progress", "--encoder", "masks", "--masks",
                 f"a person={tmp_path / 'masks'}", "--epochs", "1", "--samples", "2048"]) == 0
    out = capsys.readouterr().out
    assert "'a person' 3/6" in out and "3/6 annotated for every phrase" in out
    feats = [feature_store(full).load(t).astype(np.float32) for t in range(2)]
    layouts, offsets = camera_layouts(full, 0, feature_store(full).config["ratios"])
    rows = [slice(o, o + l.num_crops) for o, l in zip(offsets, layouts)]
    for t in range(2):
        assert np.all(feats[t][rows[1]] == 0)                                   # no evidence
        assert np.allclose(np.linalg.norm(feats[t][rows[0]], axis=1), 1, atol=2e-3)
        assert np.allclose(np.linalg.norm(feats[t][rows[2]], axis=1), 1, atol=2e-3)  # t=1: the tube's t=0 frame

    # the same two annotated cameras as the whole training rig
    sub = Scene(gaussians=full.gaussians, cameras=CameraRig.static([cams[0], cams[2]], [], 2), name="micro")
    sub = load_bundle(write_bundle(sub, tmp_path / "sub"))
    extract_features(sub, AnnotationMaskEncoder({"a person": tmp_path / "masks"}))
    for t in range(2):
        sub_feats = feature_store(sub).load(t).astype(np.float32)
        assert np.array_equal(sub_feats, np.concatenate([feats[t][rows[0]], feats[t][rows[2]]]))
    encoder = load_encoder(Path(full.root) / ENCODER_FILE)
    for mode in ("lift", "lift+refine"):
        config = DistillOptions(mode=mode, iterations=3).check()
        for t in range(2):
            a, _ = distill_timestep(full, t, encoder, feature_store(full), config)
            b, _ = distill_timestep(sub, t, encoder, feature_store(sub), config)
            assert np.isfinite(a).all() and np.abs(a).sum() > 0
            np.testing.assert_allclose(a, b, atol=1e-5)

    # the field lifted from two annotated views still finds the person from the held-out camera
    field = load_bundle(full.root)
    engine = open_query_engine(field)
    test_cam = field.cameras.cameras(0, "test")[0]
    rel = engine.relevancy_map("a person", test_cam, 0, outputs=("relevancy",))["relevancy"]
    gt = masks[(test_cam.name, 0)]
    assert average_precision(rel.ravel(), gt.ravel()) > 0.7


def test_no_view_with_evidence_leaves_zero_latents(tmp_path):
    """A timestep no annotated frame reaches (its tube holds none) gets zero latents, like Gaussians no
    training camera sees; the timesteps with evidence are lifted."""
    from fourlegs_engine.language.autoencoder import ENCODER_FILE, load_encoder
    from fourlegs_engine.language.distill import DistillOptions, distill_timestep

    scene = load_bundle(micro_bundle(tmp_path / "scene", T=6))
    cams = scene.cameras.cameras(0, "train")
    write_masks(tmp_path / "masks", {(c.name, 0): render_label_coverage(scene, c, 0)[1].numpy() > 0.5 for c in cams})
    extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "masks"}))
    store = feature_store(scene)
    assert np.abs(store.load(3).astype(np.float32)).sum() > 0        # tube t-4..t+3, clipped to 0..5, holds t=0
    assert not np.any(store.load(5).astype(np.float32))              # tube 1..8 holds no annotated frame
    train_autoencoder(scene, AETrainOptions(epochs=1, samples=1024, heldout_samples=128, batch_size=256))
    encoder = load_encoder(Path(scene.root) / ENCODER_FILE)
    for mode in ("lift", "optimize"):
        config = DistillOptions(mode=mode, iterations=2).check()
        latents, timing = distill_timestep(scene, 5, encoder, store, config)
        assert latents.shape == (scene.num_gaussians, 128) and not np.any(latents)
    latents, _ = distill_timestep(scene, 0, encoder, store, DistillOptions(mode="lift").check())
    assert np.isfinite(latents).all() and np.abs(latents).sum() > 0


def test_query_reads_the_recorded_encoder_and_accepts_the_same_flags(tmp_path, capsys):
    """`fourlegs query` on a mask-distilled field: no encoder flags needed (the field records its encoder);
    the flags of `fourlegs language` give the same answer; another encoder is one clear line."""
    import json

    bundle = micro_bundle(tmp_path / "scene", T=2)
    person_masks(load_bundle(bundle), tmp_path / "masks")
    flags = ["--encoder", "masks", "--masks", f"a person={tmp_path / 'masks'}"]
    assert main(["language", str(bundle), "--no-progress", *flags, "--epochs", "1", "--samples", "2048"]) == 0
    capsys.readouterr()
    answers = []
    for i, extra in enumerate(([], flags)):
        out = tmp_path / f"q{i}.json"
        assert main(["query", str(bundle), "a person", "--json", str(out), "--scale", "0.5", *extra]) == 0
        answers.append(json.loads(out.read_text()))
    assert answers[0]["temporal"] == answers[1]["temporal"] and answers[0]["best_view"] == answers[1]["best_view"]
    scores = np.asarray(answers[0]["temporal"]["scores"])
    assert scores.shape == (2,) and np.isfinite(scores).all()
    capsys.readouterr()
    assert main(["query", str(bundle), "a person", "--encoder", "simulated"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'masks' encoder" in err[0] and "--encoder" in err[0]


@pytest.mark.slow
@pytest.mark.skipif(not (REAL / "seg").is_dir(), reason=f"shared real data absent ({REAL})")
def test_real_capture_through_the_readme_chain(tmp_path, capsys):
    """The README's "your own capture" sequence on the real capture, small: fit six cameras x two
    timesteps at 80x45, the seg/ masks as "a person" (two cameras' masks left out: they do not vote),
    query, highlight video. Each command succeeds; the field, the query and the video are real."""
    import json
    import shutil

    cams = ["1", "5", "9", "14", "20", "25"]
    masks = tmp_path / "seg"
    for cam in cams[:4]:
        (masks / cam).mkdir(parents=True)
        for t in range(2):
            shutil.copy(REAL / "seg" / cam / f"{t:06d}.png", masks / cam / f"{t:06d}.png")
    scene, out = tmp_path / "my_scene", tmp_path / "out"
    assert main(["fit", str(REAL), "-o", str(scene), "--timesteps", "0:2", "--cameras", ",".join(cams),
                 "--resolution-scale", "0.125", "--first-iterations", "15", "--iterations", "2",
                 "--max-gaussians", "6000", "--init-foreground", "3000", "--init-background", "2000"]) == 0
    capsys.readouterr()
    assert main(["language", str(scene), "--no-progress", "--encoder", "masks", "--masks", f"a person={masks}",
                 "--epochs", "2", "--samples", "8192", "--view-scale", "0.25"]) == 0
    printed = capsys.readouterr()
    assert "'a person' 8/12; 8/12 annotated for every phrase" in printed.out
    assert printed.err.count("Warning") == 0
    assert main(["query", str(scene), "a person", "--json", str(out / "person.json"), "--scale", "0.25"]) == 0
    answer = json.loads((out / "person.json").read_text())
    assert np.isfinite(answer["temporal"]["scores"]).all() and len(answer["temporal"]["scores"]) == 2
    capsys.readouterr()
    assert main(["highlight", str(scene), "a person", "--preset", "broadcast", "-o", str(out),
                 "--resolution", "64x36", "--fps", "4"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["scene"]["num_timesteps"] == 2 and Path(report["outputs"]["video"]).stat().st_size > 0
    assert report["localization"]["scores"] == pytest.approx(answer["temporal"]["scores"], abs=1e-4)


def test_readme_own_capture_sequence_is_the_cli():
    """The README's "your own capture" block: each line a `fourlegs` command the CLI parses, in the order
    fit, language, query, highlight, all on the same scene; the README stays within 200 lines."""
    import re
    import shlex

    from fourlegs_engine.commands.main import build_parser

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    section = text.split("## Your own capture", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    variables = {}
    commands = []
    for line in block.splitlines():
        line = line.split("  #", 1)[0].strip()
        if "=" in line.split()[0]:
            name, value = line.split("=", 1)
            variables[name] = value
            continue
        for name, value in variables.items():
            line = line.replace("$" + name, value)
        argv = shlex.split(line)
        assert argv[0] == "fourlegs"
        args = build_parser().parse_args(argv[1:])
        commands.append((argv[1], args))
    assert [c for c, _ in commands] == ["fit", "language", "query", "highlight"]
    fit, language, query, highlight = (a for _, a in commands)
    assert fit.output == language.scene == query.scene[0] == highlight.scene
    assert language.encoder == "masks" and language.masks[0].startswith("a person=")
    assert query.scene[1] == highlight.query == "a person"


def test_evidence_counts_match_the_files_present(tmp_path_factory):
    """For any pattern of mask files of two phrases over 3 cameras x 5 timesteps: the per-phrase counts, the
    annotated camera-timesteps (both phrases present) and annotated() follow the files exactly."""
    from types import SimpleNamespace

    from hypothesis import given, settings, strategies as st

    cams = [SimpleNamespace(name=f"c{i}", width=4, height=3) for i in range(3)]
    cells = [(c.name, t) for c in cams for t in range(5)]

    @settings(max_examples=12)
    @given(st.sets(st.sampled_from(cells), min_size=1), st.sets(st.sampled_from(cells), min_size=1))
    def check(first, second):
        root = tmp_path_factory.mktemp("masks")
        ones = np.ones((3, 4), bool)
        write_masks(root / "a", {cell: ones for cell in first})
        write_masks(root / "b", {cell: ones for cell in second})
        enc = AnnotationMaskEncoder({"a person": root / "a", "a ball": root / "b"})
        both = first & second
        if not both:
            with pytest.raises(InputError, match="no camera-timestep has the masks of every phrase"):
                enc.check_masks(cams, 5)
            return
        enc.check_masks(cams, 5)
        summary = enc.evidence_summary()
        assert summary["per_phrase"] == {"a person": len(first), "a ball": len(second)}
        assert summary["annotated"] == len(both) and summary["camera_timesteps"] == 15
        for name, t in cells:
            assert enc.annotated(name, t) == ((name, t) in both)
            frame = enc.coverage_frame(t, cams[int(name[1])])
            assert (frame is None) == ((name, t) not in both)
            if frame is not None:
                assert frame.shape == (2, 3, 4) and bool(frame.all())

    check()


def test_masks_added_later_make_the_features_stale(tmp_path):
    """Features extracted from masks of some views are not silently reused once more views are annotated:
    the extraction refuses them (config mismatch) until --overwrite, then the new view carries evidence."""
    from fourlegs_engine.errors import ConfigMismatchError

    scene = load_bundle(micro_bundle(tmp_path / "scene", T=2))
    cams = scene.cameras.cameras(0, "train")
    person_masks(scene, tmp_path / "masks")
    import shutil
    shutil.move(str(tmp_path / "masks" / cams[2].name), str(tmp_path / "later"))
    extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "masks"}))
    assert not np.any(feature_store(scene).load(0)[-1])                  # camera 2's last crop: no evidence
    shutil.move(str(tmp_path / "later"), str(tmp_path / "masks" / cams[2].name))
    with pytest.raises(ConfigMismatchError):
        extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "masks"}))
    extract_features(scene, AnnotationMaskEncoder({"a person": tmp_path / "masks"}), overwrite=True)
    assert np.any(feature_store(scene).load(0)[-1])


def test_unannotated_views_cost_no_storage_and_the_held_out_camera_has_masks(tmp_path, capsys):
    """Masks of two of three training cameras: the third camera's rows are not stored (a row index instead)
    and read back as zeros; the autoencoder holds out the last camera that has masks, trains on a sample
    balanced over feature directions, and `language` names the held-out camera and its cosine."""
    import json
    import shutil

    full = load_bundle(micro_bundle(tmp_path / "full", T=2))
    person_masks(full, tmp_path / "masks")
    cams = full.cameras.cameras(0, "train")
    shutil.rmtree(tmp_path / "masks" / cams[-1].name)  # the default held-out camera has no masks
    assert main(["language", str(full.root), "--no-progress", "--encoder", "masks", "--masks",
                 f"a person={tmp_path / 'masks'}", "--epochs", "1", "--samples", "1024"]) == 0
    out = capsys.readouterr().out
    store = feature_store(full)
    for t in range(2):
        dense = store.load(t)
        stored = np.load(store.step_path(t), allow_pickle=False)
        rows = np.load(store.rows_path(t), allow_pickle=False)
        kept = np.flatnonzero(np.any(dense != 0, axis=1))
        assert rows[0] == dense.shape[0] and np.array_equal(rows[1:], kept)
        assert stored.shape[0] == kept.size < dense.shape[0]   # the unannotated camera's rows cost nothing
        np.testing.assert_array_equal(stored, dense[kept])
    report = json.loads((full.root / "language" / "autoencoder.json").read_text())
    held = len(cams) - 2
    assert report["heldout_camera"] == held and report["heldout_cosine"] is not None
    assert report["balance"] == "directions" and report["config"]["balance"] == "directions"
    assert f"held-out camera {held} cosine {report['heldout_cosine']:.4f}" in out and "None" not in out
    assert "query index (sketch rank 32) ready" in out  # the default query path's index, built with the field
    assert (full.root / "language" / "sketch_32.npz").is_file()
    from fourlegs_bench.ae_directions import round_trip_relevancy

    from fourlegs_engine.language.autoencoder import DECODER_FILE, ENCODER_FILE, load_decoder, load_encoder

    rows = round_trip_relevancy(full.root)  # what the autoencoder makes of the phrase's own feature
    assert [(r["phrase"], r["coverage"]) for r in rows] == [("a person", 0.34), ("a person", 1.0)]
    feature = phrase_embedding("a person")  # full coverage: the phrase's own embedding
    with torch.no_grad():
        back = load_decoder(full.root / DECODER_FILE)(load_encoder(full.root / ENCODER_FILE)(
            torch.tensor(feature[None], dtype=torch.float32)))[0].double().numpy()
    assert rows[1]["cosine"] == pytest.approx(float(back @ feature / np.linalg.norm(back)), abs=1e-5)
    assert all(r["before"]["a person"] > 0.9 and 0 <= r["after"]["a person"] <= 1 and r["balance"] == "directions"
               for r in rows)


def test_balanced_sample_gives_a_rare_direction_an_equal_share():
    from fourlegs_engine.language.ae_sample import balance_directions

    rng = np.random.default_rng(0)
    common = np.tile(np.eye(6)[0], (990, 1)) + rng.normal(scale=0.05, size=(990, 6))
    rare = np.tile(np.eye(6)[3], (10, 1)) + rng.normal(scale=0.05, size=(10, 6))
    pool = torch.from_numpy(np.concatenate([common, rare]).astype(np.float32))
    out = balance_directions(pool, 400, 2, np.random.default_rng(1))
    assert out.shape == (400, 6)
    is_rare = out[:, 3] > 0.5
    assert int(is_rare.sum()) == 200                   # 1 % of the pool, half of the sample
    assert {tuple(r) for r in out[is_rare].numpy().round(6)} <= {tuple(r) for r in pool[990:].numpy().round(6)}
    assert AETrainOptions().resolved_balance("masks") == "directions"
    assert AETrainOptions().resolved_balance("viclip") == "none" and "balance" not in AETrainOptions().to_dict()
    with pytest.raises(InputError, match="unknown balance"):
        AETrainOptions(balance="rare").resolved_balance("masks")
