"""One meaning per option across the commands: ``--demo`` is a flag everywhere, effect selection is the same
pair of options wherever a highlight is planned, and parsing never rewrites the parsed arguments."""
from __future__ import annotations

import argparse
import copy

import pytest

from fourlegs_engine.commands.main import build_parser
from fourlegs_engine.errors import InputError
from fourlegs_engine.highlights.presets import load_preset


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    """Every ``fourlegs`` subcommand (benchmarks included) by its path, e.g. "plan", "bench main-job"."""
    out = {}

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out[f"{prefix}{name}"] = sub
                    walk(sub, f"{prefix}{name} ")

    walk(build_parser(), "")
    return out


def _option(parser: argparse.ArgumentParser, flag: str) -> argparse.Action | None:
    return next((a for a in parser._actions if flag in a.option_strings), None)


def test_demo_is_a_flag_in_every_command():
    commands = _subcommands()
    with_demo = {name: _option(p, "--demo") for name, p in commands.items() if _option(p, "--demo") is not None}
    assert {"info", "plan", "query", "highlight", "language"} <= set(with_demo)
    assert {name: a.nargs for name, a in with_demo.items() if a.nargs != 0} == {}


def test_plan_and_highlight_select_effects_with_the_same_options():
    commands = _subcommands()
    for flag in ("--effects", "--no-effect"):
        plan, highlight = _option(commands["plan"], flag), _option(commands["highlight"], flag)
        assert plan is not None and highlight is not None, flag
        assert (type(plan), plan.nargs, plan.default, plan.help) == \
            (type(highlight), highlight.nargs, highlight.default, highlight.help)


def test_plan_takes_its_query_beside_the_demo_flag():
    args = build_parser().parse_args(["plan", "--demo", "a ball flying", "-o", "p.json"])
    assert args.demo is True and args.inputs == ["a ball flying"]


def test_effect_selection_keeps_and_drops_shots_by_effect():
    preset = load_preset("broadcast")
    effects = [s.effect for s in preset.shots]
    assert "zoom_in" in effects and "bullet_time" in effects
    assert [s.effect for s in preset.select_effects(keep=("zoom_in",)).shots] == ["zoom_in"]
    assert [s.effect for s in preset.select_effects(drop=("zoom_in",)).shots] == [e for e in effects if e != "zoom_in"]
    both = preset.select_effects(keep=("zoom_in", "bullet_time"), drop=("bullet_time",))
    assert [s.effect for s in both.shots] == ["zoom_in"]
    assert preset.select_effects().shots == preset.shots
    with pytest.raises(InputError, match=r"no_effect: unknown effects \['sparkles'\]"):
        preset.select_effects(drop=("sparkles",))
    with pytest.raises(InputError, match=r"effects: unknown effects \['sparkles'\]"):
        preset.select_effects(keep=("sparkles",))
    only_zoom = preset.select_effects(keep=("zoom_in",))
    with pytest.raises(InputError, match="has no shot with the effects"):
        only_zoom.select_effects(keep=("bullet_time",))


def test_highlight_job_options_carry_the_selection():
    from fourlegs_engine.commands.options import highlight_job_options

    args = _subcommands()["highlight"].parse_args(["scene", "q", "-o", "out", "--effects", "zoom_in, play",
                                                   "--no-effect", "play"])
    options = highlight_job_options(args)
    assert (options.effects, options.no_effect) == (("zoom_in", "play"), ("play",))


def test_splitting_query_inputs_leaves_the_parsed_arguments_as_they_were():
    from fourlegs_engine.commands.query import QueryInputs, _split_inputs

    args = build_parser().parse_args(["query", "a", "b", "the ball"])
    before = copy.deepcopy(vars(args))
    assert _split_inputs(args) == QueryInputs(("a", "b"), None, "the ball")
    assert vars(args) == before
    one = build_parser().parse_args(["query", "a", "the ball"])
    assert _split_inputs(one) == QueryInputs(("a",), "a", "the ball")
    demo = build_parser().parse_args(["query", "--demo", "the ball"])
    assert _split_inputs(demo) == QueryInputs((), None, "the ball")
    with pytest.raises(InputError, match="not both"):
        _split_inputs(build_parser().parse_args(["query", "--demo", "a", "the ball"]))
