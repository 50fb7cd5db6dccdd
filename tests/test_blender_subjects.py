"""The panel lists the separate things a query matches (the plan's instances), the framed ones marked."""
from __future__ import annotations

import pytest

from _blender_helpers import bl, bpy_addon  # noqa: F401

pytestmark = pytest.mark.blender


def test_generate_highlight_lists_the_plans_instances_in_the_panel(bl):
    from fourlegs_addon import importer, operators

    from fourlegs_engine.highlights.planner import plan_highlight
    from test_highlights_subjects import QUERY, _localizer, _preset, two_people

    people = two_people(T=24)
    scene, big, small = people[0], people[2], people[3]
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset(subjects=2), resolution=(64, 36)).to_dict()
    bl.context.scene.fourlegs.renderer = "FOURLEGS"
    importer.import_scene(bl.context.scene, scene)
    operators.generate_highlight(bl.context.scene, plan)
    props = bl.context.scene.fourlegs
    assert [s.gaussians for s in props.subjects] == [int(big.sum()), int(small.sum())]
    assert [s.framed for s in props.subjects] == [True, True]
    assert all(1.5 < s.height < 2.0 for s in props.subjects)
    assert props.subject_index == 0 and hasattr(bl.types, "FOURLEGS_UL_subjects")
    # one framed subject: the second is listed, not framed
    plan = plan_highlight(scene, _localizer(people), QUERY, _preset(), resolution=(64, 36)).to_dict()
    operators.generate_highlight(bl.context.scene, plan)
    assert [s.framed for s in props.subjects] == [True, False]
