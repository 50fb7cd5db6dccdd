"""Compositor setup for the plan's background desaturation (built only when the plan has it).

Graph (Blender 5.0: a ``CompositorNodeTree`` node group assigned to ``scene.compositing_node_group``;
4.2-4.5: ``scene.use_nodes`` + ``scene.node_tree`` + a Composite node)::

    Render Layers.Image ──────────────────────────────┬──────────── Mix.A
                       └─ Hue/Saturation (sat 0) ────────────────── Mix.B ── output "Image"
    Render Layers.Relevancy ─ Map Range (smoothstep 0.4→0.6) ─ 1-x ─ × weight ─ Mix.Factor

``weight`` is a Value node keyed per frame from ``plan["desaturate"]["weights"]`` (fade in/out,
times ``strength``); outside the desaturation ranges it is 0, so the frame passes unchanged.
"""
from __future__ import annotations

from typing import Any, Optional

import bpy

from .keyframes import GENERATED_KEY, write_fcurve

TREE_NAME = "4-LEGS Compositor"
RELEVANCY_PASS = "Relevancy"
WEIGHT_NODE = "Desaturation Weight"
MASK_LOW, MASK_HIGH = 0.4, 0.6  # relevancy 0.5 is the paper's threshold; soften the edge around it
IS_50 = bpy.app.version >= (5, 0, 0)
# 5.0 compositor trees use the shared shader utility nodes; 4.x had compositor-specific ones
MATH_NODE = "ShaderNodeMath" if IS_50 else "CompositorNodeMath"
VALUE_NODE = "ShaderNodeValue" if IS_50 else "CompositorNodeValue"
MAP_RANGE_NODE = "ShaderNodeMapRange" if IS_50 else "CompositorNodeMapRange"


def _socket(sockets, identifier: str):
    """A node socket by identifier (names repeat on ShaderNodeMix: three inputs are called 'A')."""
    for sock in sockets:
        if sock.identifier == identifier:
            return sock
    raise KeyError(identifier)


def frame_weights(plan: dict[str, Any]) -> dict[int, float]:
    """Desaturation strength per timeline frame (0 outside the ranges), from the plan.

    Uses ``desaturate.weights`` when given ({"frame": w}); otherwise builds linear fades of
    ``fade_in``/``fade_out`` frames inside each range. Multiplied by ``strength``.
    """
    desat = plan.get("desaturate")
    if not desat:
        return {}
    strength = float(desat.get("strength", 1.0))
    out = {f: 0.0 for f in range(int(plan["frame_start"]), int(plan["frame_end"]) + 1)}
    weights = desat.get("weights") or {}
    if weights:
        for frame, w in weights.items():
            out[int(frame)] = min(max(float(w), 0.0), 1.0) * strength
        return out
    fin, fout = int(desat.get("fade_in", 0)), int(desat.get("fade_out", 0))
    for a, b in desat.get("ranges", []):
        for f in range(int(a), int(b) + 1):
            w = 1.0
            if fin > 0:
                w = min(w, (f - a + 1) / (fin + 1))
            if fout > 0:
                w = min(w, (b - f + 1) / (fout + 1))
            out[f] = max(out.get(f, 0.0), w * strength)
    return out


def remove_compositor(scene: bpy.types.Scene) -> None:
    """Remove a compositor setup this module created (and nothing else)."""
    if IS_50:
        tree = scene.compositing_node_group
        if tree is not None and tree.get(GENERATED_KEY):
            scene.compositing_node_group = None
        for group in [g for g in bpy.data.node_groups if g.get(GENERATED_KEY) and g.bl_idname == "CompositorNodeTree"]:
            bpy.data.node_groups.remove(group)
    else:
        tree = scene.node_tree
        if tree is not None and tree.get(GENERATED_KEY):
            tree.nodes.clear()
            scene.use_nodes = False


def has_desaturation(scene: bpy.types.Scene) -> bool:
    tree = compositor_tree(scene)
    return tree is not None and tree.get(GENERATED_KEY) and WEIGHT_NODE in tree.nodes


def desaturation_at(scene: bpy.types.Scene, frame: int) -> float:
    """The keyed desaturation strength at ``frame`` (0 when there is none): read from the F-curve, so it
    follows the keys wherever an editor moved them on the timeline."""
    tree = compositor_tree(scene)
    if tree is None or not tree.get(GENERATED_KEY) or WEIGHT_NODE not in tree.nodes:
        return 0.0
    from .keyframes import find_fcurve

    fc = find_fcurve(tree, f'nodes["{WEIGHT_NODE}"].outputs[0].default_value', 0)
    if fc is None:
        return float(tree.nodes[WEIGHT_NODE].outputs[0].default_value)
    return float(fc.evaluate(frame))


def compositor_tree(scene: bpy.types.Scene):
    return scene.compositing_node_group if IS_50 else (scene.node_tree if scene.use_nodes else None)


def build_compositor(scene: bpy.types.Scene, plan: dict[str, Any], mask_layer: Optional[str] = None):
    """Create the desaturation graph if ``plan`` has desaturation; otherwise remove ours. Returns the tree or None.

    The Relevancy pass comes from the picture's own view layer (the 4-LEGS Splats engine declares it
    when ``view_layer.fourlegs_relevancy`` is set, see ``render_engine``) or, with ``mask_layer``, from
    that view layer's AOV (EEVEE and Cycles, see ``native_render``).
    """
    remove_compositor(scene)
    if not plan.get("desaturate"):
        return None
    if IS_50:
        tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
        tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        out = tree.nodes.new("NodeGroupOutput")
        out_socket = out.inputs[0]
        scene.compositing_node_group = tree
    else:  # Blender 4.2 - 4.5
        scene.use_nodes = True
        tree = scene.node_tree
        tree.nodes.clear()
        out = tree.nodes.new("CompositorNodeComposite")
        out_socket = out.inputs["Image"]
    tree[GENERATED_KEY] = True
    nodes, links = tree.nodes, tree.links
    layers = nodes.new("CompositorNodeRLayers")
    layers.scene = scene
    mask_layers = layers
    if mask_layer is not None:
        layers.layer = next(v.name for v in scene.view_layers if v.name != mask_layer)
        mask_layers = nodes.new("CompositorNodeRLayers")
        mask_layers.scene, mask_layers.layer = scene, mask_layer
        mask_layers.location = (-600, -300)
    if RELEVANCY_PASS not in mask_layers.outputs:
        raise RuntimeError("the render engine does not provide a Relevancy pass: set the scene's render "
                           "engine to '4-LEGS Splats' before building the compositor")
    gray = nodes.new("CompositorNodeHueSat")
    gray.inputs["Saturation"].default_value = 0.0
    mask = nodes.new(MAP_RANGE_NODE)
    if IS_50:
        mask.interpolation_type = "SMOOTHSTEP"
        mask.clamp = True
    else:
        mask.use_clamp = True
    mask.inputs["From Min"].default_value, mask.inputs["From Max"].default_value = MASK_LOW, MASK_HIGH
    invert = nodes.new(MATH_NODE)
    invert.operation = "SUBTRACT"
    invert.inputs[0].default_value = 1.0
    weight = nodes.new(VALUE_NODE)
    weight.name = weight.label = WEIGHT_NODE
    scale = nodes.new(MATH_NODE)
    scale.operation = "MULTIPLY"
    if IS_50:
        mix = nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix_a, mix_b, mix_f = (_socket(mix.inputs, "A_Color"), _socket(mix.inputs, "B_Color"),
                               _socket(mix.inputs, "Factor_Float"))
        mix_out = _socket(mix.outputs, "Result_Color")
    else:
        mix = nodes.new("CompositorNodeMixRGB")
        mix_f, mix_a, mix_b, mix_out = mix.inputs[0], mix.inputs[1], mix.inputs[2], mix.outputs[0]
    links.new(layers.outputs["Image"], gray.inputs["Image"])
    links.new(layers.outputs["Image"], mix_a)
    links.new(gray.outputs["Image"], mix_b)
    links.new(mask_layers.outputs[RELEVANCY_PASS], mask.inputs[0])
    links.new(mask.outputs[0], invert.inputs[1])
    links.new(invert.outputs[0], scale.inputs[0])
    links.new(weight.outputs[0], scale.inputs[1])
    links.new(scale.outputs[0], mix_f)
    links.new(mix_out, out_socket)
    for node, loc in ((layers, (-600, 0)), (gray, (-300, 150)), (mask, (-300, -150)), (invert, (-100, -150)),
                      (weight, (-100, -350)), (scale, (100, -200)), (mix, (300, 0)), (out, (550, 0))):
        node.location = loc

    weights = frame_weights(plan)
    frames = sorted(weights)
    weight.outputs[0].default_value = 0.0
    action = bpy.data.actions.new("4-LEGS Desaturation")
    action[GENERATED_KEY] = True
    write_fcurve(tree, action, f'nodes["{WEIGHT_NODE}"].outputs[0].default_value', 0, frames,
                 [weights[f] for f in frames], ["LINEAR"] * len(frames))
    scene.render.use_compositing = True
    return tree
