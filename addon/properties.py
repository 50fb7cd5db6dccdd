"""Add-on state stored on the Scene (``scene.fourlegs``): source, query, results, effects, output.

``timestep`` is the animatable *scene time* of the 4D scene, independent of the timeline frame:
keyframing it constant while the camera moves gives bullet-time, keyframing it slower than the
timeline gives slow motion. A frame-change handler (``importer.on_frame_change``) shows it.
"""
from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)


_PRESET_ITEMS: list[tuple[str, str, str]] = []  # Blender needs Python to keep dynamic enum strings alive


def _preset_items(self, context):
    from . import planning

    _PRESET_ITEMS[:] = [(name, name.replace("_", " ").title(), f"{name} preset")
                        for name in planning.preset_names()]
    return _PRESET_ITEMS


def _timestep_changed(self, context):
    from . import importer
    importer.update_scene_objects(context.scene)


def _segment_picked(self, context):
    """Selecting a segment in the list shows its first timestep and makes it the one the panel reports."""
    if not 0 <= self.segment_index < len(self.segments):
        return
    seg = self.segments[self.segment_index]
    self.segment_start, self.segment_end = seg.start, seg.end
    self.timestep = float(seg.start)


class FourlegsSegment(bpy.types.PropertyGroup):
    """One positive run of s_t: timesteps ``start``-``end`` (inclusive) with its peak score."""
    start: IntProperty(name="Start", default=0)
    end: IntProperty(name="End", default=0)
    peak_score: FloatProperty(name="Peak s_t", default=0.0)


class FourlegsSubject(bpy.types.PropertyGroup):
    """One separate thing the query matches at the peak (an instance of the plan's ``localization.instances``),
    best first; ``framed``: the highlight gives it its own zoom and orbit."""
    gaussians: IntProperty(name="Gaussians", default=0)
    height: FloatProperty(name="Height", default=0.0, subtype="DISTANCE")
    mass: FloatProperty(name="Relevancy Mass", default=0.0)
    framed: BoolProperty(name="Framed", default=False)


class FourlegsSceneProps(bpy.types.PropertyGroup):
    # --- source
    source_path: StringProperty(name="Scene", description="Scene bundle, params.npz directory or PLY file/directory",
                                subtype="FILE_PATH", default="")
    splat_object: PointerProperty(name="Splats", type=bpy.types.Object,
                                  description="The imported point-cloud object of the 4D scene")
    timestep: FloatProperty(name="Scene Time", description="Timestep of the 4D scene shown (keyframable; "
                            "hold it for bullet-time)", default=0.0, min=0.0, update=_timestep_changed,
                            options={"ANIMATABLE"})
    num_timesteps: IntProperty(name="Timesteps", default=0, min=0)
    # --- query
    query: StringProperty(name="Query", description="What to find, e.g. 'a ball flying in the air'", default="")
    running: BoolProperty(name="Running", default=False, options={"SKIP_SAVE"})
    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR",
                            options={"SKIP_SAVE"})
    status: StringProperty(name="Status", default="")
    found: BoolProperty(name="Found", default=False)
    segment_start: IntProperty(name="Segment Start", default=-1)
    segment_end: IntProperty(name="Segment End", default=-1)
    peak: IntProperty(name="Peak", default=-1)
    best_view: StringProperty(name="Best View", default="")
    segments: CollectionProperty(type=FourlegsSegment, name="Segments",
                                 description="Every segment where the query was found")
    segment_index: IntProperty(name="Segment", default=-1, update=_segment_picked)
    subjects: CollectionProperty(type=FourlegsSubject, name="Subjects",
                                 description="The separate things the query matches at the peak, best first")
    subject_index: IntProperty(name="Subject", default=-1)
    # --- encoder of fields distilled with ViCLIP (what `--checkpoint` / `--vocab` give the commands)
    encoder_checkpoint: StringProperty(name="ViCLIP Weights", subtype="FILE_PATH", default="",
                                       description="ViClip-InternVid-10M-FLT.pth, a .safetensors file or a "
                                                   "ViCLIP-*-hf directory (never downloaded)")
    encoder_vocab: StringProperty(name="ViCLIP Vocabulary", subtype="FILE_PATH", default="",
                                  description="CLIP BPE vocabulary bpe_simple_vocab_16e6.txt.gz")
    # --- highlight
    preset: EnumProperty(name="Preset", description="Highlight preset of the planner", items=_preset_items)
    use_bullet_time: BoolProperty(name="Bullet Time", default=True)
    use_zoom_in: BoolProperty(name="Zoom In", default=True)
    use_desaturate: BoolProperty(name="Desaturate Background", default=True)
    use_blur: BoolProperty(name="Blur Background", default=True,
                           description="Keep the preset's blurred-background shots (presets such as broadcast_blur)")
    renderer: EnumProperty(
        name="Renderer", default="NATIVE" if bpy.app.version >= (5, 3, 0) else "FOURLEGS",
        items=[("NATIVE", "EEVEE / Cycles", "Blender renders the splats with meshes, lights and its compositor "
                "(Blender 5.3+); the desaturation mask is a view layer Blender renders too"),
               ("FOURLEGS", "4-LEGS Splats", "The add-on's exact Gaussian rasterizer (any Blender; meshes are not "
                "drawn)")])
    # --- output
    output_path: StringProperty(name="Output", subtype="FILE_PATH", default="//highlight.mp4")
    output_format: EnumProperty(name="Format", items=[("MP4", "MP4 (H.264)", "One video file"),
                                                       ("PNG", "PNG sequence", "One PNG per frame"),
                                                       ("EXR", "OpenEXR sequence", "One EXR per frame")],
                                default="MP4")
    overwrite: BoolProperty(name="Overwrite", default=False, description="Replace an existing output")


classes = (FourlegsSegment, FourlegsSubject, FourlegsSceneProps)


def register() -> None:
    bpy.types.Scene.fourlegs = PointerProperty(type=FourlegsSceneProps)


def unregister() -> None:
    del bpy.types.Scene.fourlegs
