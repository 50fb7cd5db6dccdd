"""Presets: the shipped TOML files, validation errors naming file and field, lookup order."""
from __future__ import annotations

from pathlib import Path

import pytest

from fourlegs_engine.errors import InputError
from fourlegs_engine.highlights import presets as presets_mod
from fourlegs_engine.highlights.presets import available_presets, load_preset, parse_preset

SHIPPED = {
    "broadcast": ["play", "zoom_in", "bullet_time", "desaturate_background"],
    "bullet_time_only": ["bullet_time"],
    "subtle_desaturate": ["desaturate_background"],
    "social_vertical": ["play", "zoom_in", "bullet_time", "desaturate_background"],
}


@pytest.mark.parametrize("name,effects", sorted(SHIPPED.items()))
def test_shipped_presets_load(name, effects):
    p = load_preset(name)
    assert p.name == name and [s.effect for s in p.shots] == effects
    assert p.description and Path(p.source).parent == presets_mod.REPO_PRESETS


def test_social_vertical_is_portrait_9_16():
    w, h = load_preset("social_vertical").resolution
    assert w * 16 == h * 9


def test_defaults_are_filled_in():
    p = load_preset("bullet_time_only")
    params = p.shots[0].params
    assert params["arc_deg"] == 360.0 and params["radius_scale"] == 1.0 and params["from"] == "peak"


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("body,field,problem", [
    ('fps = 24\nbogus = 1\n[[shots]]\neffect = "play"\n', "bogus", "unknown key"),
    ('fps = "fast"\n[[shots]]\neffect = "play"\n', "fps", "frames per second"),
    ('resolution = [1280]\n[[shots]]\neffect = "play"\n', "resolution", "[width, height]"),
    ('fps = 24\n', "shots", "at least one"),
    ('[[shots]]\nname = "a"\n', "shots[0].effect", "missing 'effect'"),
    ('[[shots]]\neffect = "explode"\n', "shots[0].effect", "unknown effect 'explode'"),
    ('[[shots]]\neffect = "bullet_time"\narc_deg = "wide"\n', "shots[0].arc_deg", "must be a number"),
    ('[[shots]]\neffect = "bullet_time"\narc_deg = 5000\n', "shots[0].arc_deg", "must be <= 1080"),
    ('[[shots]]\neffect = "zoom_in"\nfactor = 0.5\n', "shots[0].factor", "must be >= 1"),
    ('[[shots]]\neffect = "zoom_in"\nmode = "warp"\n', "shots[0].mode", "must be one of dolly, focal"),
    ('[[shots]]\neffect = "zoom_in"\narc_deg = 90\n', "shots[0].arc_deg", "unknown parameter for effect 'zoom_in'"),
    ('[[shots]]\neffect = "play"\nfrom = "kickoff"\n', "shots[0].from", "must be one of start"),
    ('[[shots]]\neffect = "desaturate_background"\nfade_in_frames = 2.5\n', "shots[0].fade_in_frames",
     "whole number"),
    ('[[shots]]\neffect = "play"\n[[shots]]\neffect = "play"\n', "shots[1].name", "duplicate shot name"),
    ('[[shots]]\neffect = "play"\ndepth_of_field = 1\n', "shots[0].depth_of_field", "true or false"),
    ('[[shots]]\neffect = "play"\neasing = "bouncy"\n', "shots[0].easing", "must be one of"),
])
def test_bad_presets_name_file_field_and_problem(tmp_path, body, field, problem):
    path = write(tmp_path, "bad", body)
    with pytest.raises(InputError) as info:
        load_preset(str(path))
    err = info.value
    assert err.file == str(path) and err.field == field and problem in err.problem
    assert str(path) in str(err) and field in str(err)


def test_invalid_toml_names_the_file(tmp_path):
    path = write(tmp_path, "broken", "[[shots]\neffect = play\n")
    with pytest.raises(InputError, match="not valid TOML") as info:
        load_preset(str(path))
    assert info.value.file == str(path)


def test_unknown_preset_lists_the_available_ones():
    with pytest.raises(InputError, match="unknown preset 'nope'; available: broadcast, broadcast_blur, bullet_time_only"):
        load_preset("nope")


def test_user_directories_come_first(tmp_path, monkeypatch):
    user = tmp_path / "user"
    user.mkdir()
    write(user, "broadcast", 'description = "mine"\n[[shots]]\neffect = "bullet_time"\n')
    write(user, "orbit_twice", '[[shots]]\neffect = "bullet_time"\narc_deg = 720\n')
    assert load_preset("broadcast", [user]).description == "mine"
    assert load_preset("broadcast").description != "mine"
    env = tmp_path / "env"
    env.mkdir()
    write(env, "env_only", '[[shots]]\neffect = "play"\n')
    monkeypatch.setenv("FOURLEGS_PRESETS", str(env))
    found = available_presets([user])
    assert found["orbit_twice"].parent == user and found["env_only"].parent == env
    assert found["bullet_time_only"].parent == presets_mod.REPO_PRESETS
    assert load_preset("env_only").shots[0].effect == "play"
    assert load_preset("orbit_twice", [user]).shots[0].params["arc_deg"] == 720


def test_packaged_copy_is_found_when_the_repository_presets_are_absent(tmp_path, monkeypatch):
    packaged = tmp_path / "fourlegs_engine" / "highlights" / "presets"
    packaged.mkdir(parents=True)
    write(packaged, "broadcast", (presets_mod.REPO_PRESETS / "broadcast.toml").read_text())
    monkeypatch.setattr(presets_mod, "REPO_PRESETS", tmp_path / "missing")
    monkeypatch.setattr(presets_mod, "PACKAGED_PRESETS", packaged)
    monkeypatch.delenv("FOURLEGS_PRESETS", raising=False)
    assert set(available_presets()) == {"broadcast"}
    assert Path(load_preset("broadcast").source).parent == packaged


def test_parse_preset_from_a_dict_and_with_shots():
    p = parse_preset({"shots": [{"effect": "play"}, {"effect": "zoom_in", "name": "z"}]}, default_name="x")
    assert p.name == "x" and p.fps == 24 and p.resolution == (1280, 720)
    assert [s.name for s in p.with_shots(["zoom_in"]).shots] == ["z"]
