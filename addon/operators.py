"""Every operator of the 4-LEGS panel, gathered for registration; each feature has its own module:
import (:mod:`.import_ops`), query and scene ranking (:mod:`.query_ops`), language field
(:mod:`.prepare`), highlight (:mod:`.highlight_ops`), render (:mod:`.render_ops`) and the Cancel
button of the job runner (:mod:`.jobs`). The headless job calls the highlight's Blender steps,
:func:`generate_highlight` and :func:`fill_from_plan`, from here."""
from __future__ import annotations

from . import highlight_ops, import_ops, jobs, prepare, query_ops, render_ops
from .highlight_ops import fill_from_plan, generate_highlight

__all__ = ["classes", "fill_from_plan", "generate_highlight"]

classes = (*import_ops.classes, *query_ops.classes, *prepare.classes, *jobs.classes, *highlight_ops.classes,
           *render_ops.classes)
