"""View3D > Sidebar > 4-LEGS: scene status, query, results, effects, preset, highlight, render."""
from __future__ import annotations

import bpy

from . import importer, native_splats, plots, preferences, prepare, query_ops, render_engine


class FOURLEGS_PT_main(bpy.types.Panel):
    bl_idname = "FOURLEGS_PT_main"
    bl_label = "4-LEGS Highlights"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "4-LEGS"

    def draw(self, context):
        layout = self.layout
        props = context.scene.fourlegs
        missing = preferences.missing_line()
        if missing:
            box = layout.box()
            box.label(text=missing, icon="ERROR")
            box.operator("preferences.addon_show", text="Open Add-on Preferences").module = preferences.PACKAGE
        obj = props.splat_object
        if obj is None or not importer.source_key(obj):
            layout.operator("fourlegs.import_scene", icon="IMPORT")
            return
        problem = importer.missing_message(obj)
        if problem:
            layout.label(text=problem, icon="ERROR")
            layout.operator("fourlegs.relink_scene", icon="FILE_REFRESH")
        col = layout.column(align=True)
        col.label(text=f"{obj.name}: {len(obj.data.vertices):,} Gaussians", icon="POINTCLOUD_DATA")
        col.prop(props, "timestep")
        col.label(text=f"{props.num_timesteps} timesteps")
        layout.operator("fourlegs.import_scene", text="Import Another", icon="IMPORT")


class FOURLEGS_UL_segments(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        layout.label(text=f"timesteps {item.start}-{item.end}", icon="TIME")
        layout.label(text=f"peak s_t {item.peak_score:.3f}")


class FOURLEGS_UL_subjects(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        layout.label(text=f"subject {index + 1}", icon="CAMERA_DATA" if item.framed else "DOT")
        layout.label(text=f"{item.height:.2f} m, {item.gaussians} splats")


class _SidebarSubPanel:
    """Placement shared by the sub-panels of the 4-LEGS sidebar tab."""
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "4-LEGS"
    bl_parent_id = "FOURLEGS_PT_main"


class FOURLEGS_PT_query(_SidebarSubPanel, bpy.types.Panel):
    bl_idname = "FOURLEGS_PT_query"
    bl_label = "Query"

    def draw(self, context):
        layout = self.layout
        props = context.scene.fourlegs
        obj = props.splat_object
        if obj is not None and not props.running and not prepare.has_field(obj):
            box = layout.box()
            box.label(text="No language field yet (needed to query)", icon="INFO")
            box.operator("fourlegs.prepare_field", icon="PLAY")
        layout.prop(props, "query", text="")
        if props.running:
            row = layout.row(align=True)
            row.progress(factor=props.progress, type="BAR", text=props.status or "running")
            row.operator("fourlegs.cancel_query", text="", icon="CANCEL")
        else:
            layout.operator("fourlegs.run_query", icon="VIEWZOOM")
            if len(query_ops.imported_splat_objects()) > 1:
                layout.operator("fourlegs.find_best_scene", icon="SORTSIZE")
            if props.status:
                layout.label(text=props.status)
        if len(props.segments) > 1:
            layout.label(text=f"{len(props.segments)} segments (pick one to look at it):")
            layout.template_list("FOURLEGS_UL_segments", "", props, "segments", props, "segment_index", rows=3)
        if props.segment_start >= 0:
            col = layout.column(align=True)
            col.label(text=f"Segment: timesteps {props.segment_start}-{props.segment_end}")
            col.label(text=f"Peak: timestep {props.peak}")
            if props.best_view:
                col.label(text=f"Best view: {props.best_view}")
        img = bpy.data.images.get(plots.IMAGE_NAME)
        if img is not None and img.preview is not None:
            layout.template_icon(icon_value=img.preview.icon_id, scale=6.0)
        row = layout.row(align=True)
        row.operator("fourlegs.show_relevancy", text="Relevancy").show = True
        row.operator("fourlegs.show_relevancy", text="Colours").show = False
        col = layout.column(align=True)
        col.label(text="ViCLIP (fields distilled with it):")
        col.prop(props, "encoder_checkpoint", text="Weights")
        col.prop(props, "encoder_vocab", text="Vocabulary")


class FOURLEGS_PT_highlight(_SidebarSubPanel, bpy.types.Panel):
    bl_idname = "FOURLEGS_PT_highlight"
    bl_label = "Highlight"

    def draw(self, context):
        layout = self.layout
        props = context.scene.fourlegs
        layout.prop(props, "preset")
        if native_splats.available():
            layout.prop(props, "renderer")
        col = layout.column(heading="Effects", align=True)
        col.prop(props, "use_zoom_in")
        col.prop(props, "use_bullet_time")
        col.prop(props, "use_desaturate")
        col.prop(props, "use_blur")
        layout.operator("fourlegs.generate_highlight", icon="CAMERA_DATA")
        if render_engine.plan_of(context.scene) is not None:
            layout.label(text=f"Frames {context.scene.frame_start}-{context.scene.frame_end}")
        if len(props.subjects):
            layout.label(text="Subjects (camera: framed by its own shots)")
            layout.template_list("FOURLEGS_UL_subjects", "", props, "subjects", props, "subject_index", rows=2)


class FOURLEGS_PT_render(_SidebarSubPanel, bpy.types.Panel):
    bl_idname = "FOURLEGS_PT_render"
    bl_label = "Render"

    def draw(self, context):
        layout = self.layout
        props = context.scene.fourlegs
        undrawn = render_engine.undrawn_line(context.scene) if context.scene.render.engine == render_engine.ENGINE_ID else ""
        if undrawn:
            layout.label(text=undrawn, icon="INFO")
        layout.prop(props, "output_format")
        layout.prop(props, "output_path")
        layout.prop(props, "overwrite")
        if props.running and props.status.startswith(("rendering", "encoding", "writing")):
            row = layout.row(align=True)
            row.progress(factor=props.progress, type="BAR", text=props.status)
            row.operator("fourlegs.cancel_query", text="", icon="CANCEL")
        else:
            layout.operator("fourlegs.render_video", icon="RENDER_ANIMATION")


ui_lists = (FOURLEGS_UL_segments, FOURLEGS_UL_subjects)
classes = (FOURLEGS_PT_main, FOURLEGS_PT_query, FOURLEGS_PT_highlight, FOURLEGS_PT_render)
