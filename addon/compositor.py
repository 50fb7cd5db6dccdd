"""Compositor setup for the plan's background blur and desaturation (built only when the plan has one).

Graph (Blender 5.0: a ``CompositorNodeTree`` node group assigned to ``scene.compositing_node_group``;
4.2-4.5: ``scene.use_nodes`` + ``scene.node_tree`` + a Composite node)::

    Render Layers.Relevancy ─ Map Range (smoothstep 0.4→0.6) ─ 1-x = background
    Render Layers.Image ─┬──────────────────────── Mix.A
                         └─ Blur (size keyed) ──── Mix.B ── (blurred) ─┬─────────────────────── Mix.A
                            background × blur weight ─ Mix.Factor      └─ Hue/Sat (sat 0) ──── Mix.B ── output
                                                            background × desaturation weight ─ Mix.Factor

Each branch exists only when the plan has its effect. ``weight`` is a Value node keyed per frame from
``plan["desaturate"]["weights"]`` (or ``plan["blur"]["weights"]``: fade in/out, times ``strength``);
outside the ranges it is 0, so the frame passes unchanged. The blur's size is keyed too: the weight
times ``plan["blur"]["radius"]`` times the render height, in pixels.
"""
from __future__ import annotations

from typing import Any, Optional

import bpy

from .keyframes import GENERATED_KEY, write_fcurve

TREE_NAME = "4-LEGS Compositor"
RELEVANCY_PASS = "Relevancy"
WEIGHT_NODE = "Desaturation Weight"
BLUR_WEIGHT_NODE = "Blur Weight"
BLUR_NODE = "Background Blur"
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


def frame_weights(plan: dict[str, Any], effect: str = "desaturate") -> dict[int, float]:
    """Desaturation (``effect="blur"``: blur) strength per timeline frame (0 outside the ranges), from the plan.

    Uses ``<effect>.weights`` when given ({"frame": w}); otherwise builds linear fades of
    ``fade_in``/``fade_out`` frames inside each range. Multiplied by ``strength``.
    """
    desat = plan.get(effect)
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


def mask_weights(plan: dict[str, Any]) -> dict[int, float]:
    """Per timeline frame, the largest weight of the plan's masked effects (desaturation, blur): the frames
    whose relevancy mask is used are those above 0."""
    out: dict[int, float] = {}
    for effect in ("desaturate", "blur"):
        for f, w in frame_weights(plan, effect).items():
            out[f] = max(out.get(f, 0.0), w)
    return out


def has_desaturation(scene: bpy.types.Scene) -> bool:
    tree = compositor_tree(scene)
    return tree is not None and tree.get(GENERATED_KEY) and WEIGHT_NODE in tree.nodes


def has_masking(scene: bpy.types.Scene) -> bool:
    """The add-on's compositor graph is there with a desaturation or a blur."""
    tree = compositor_tree(scene)
    return bool(tree is not None and tree.get(GENERATED_KEY)
                and (WEIGHT_NODE in tree.nodes or BLUR_WEIGHT_NODE in tree.nodes))


def _keyed_weight(scene: bpy.types.Scene, node_name: str, frame: int) -> float:
    tree = compositor_tree(scene)
    if tree is None or not tree.get(GENERATED_KEY) or node_name not in tree.nodes:
        return 0.0
    from .keyframes import find_fcurve

    fc = find_fcurve(tree, f'nodes["{node_name}"].outputs[0].default_value', 0)
    if fc is None:
        return float(tree.nodes[node_name].outputs[0].default_value)
    return float(fc.evaluate(frame))


def desaturation_at(scene: bpy.types.Scene, frame: int) -> float:
    """The keyed desaturation strength at ``frame`` (0 when there is none): read from the F-curve, so it
    follows the keys wherever an editor moved them on the timeline."""
    return _keyed_weight(scene, WEIGHT_NODE, frame)


def blur_at(scene: bpy.types.Scene, frame: int) -> float:
    """The keyed blur weight at ``frame`` (0 when there is none), like :func:`desaturation_at`."""
    return _keyed_weight(scene, BLUR_WEIGHT_NODE, frame)


def mask_at(scene: bpy.types.Scene, frame: int) -> float:
    """The largest keyed weight of the masked effects at ``frame``: the relevancy mask is used where > 0."""
    return max(desaturation_at(scene, frame), blur_at(scene, frame))


def compositor_tree(scene: bpy.types.Scene):
    return scene.compositing_node_group if IS_50 else (scene.node_tree if scene.use_nodes else None)


def _new_tree(scene: bpy.types.Scene):
    """A fresh compositor tree of ours and the socket its picture goes to."""
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
    out.location = (900, 0)
    tree[GENERATED_KEY] = True
    return tree, out_socket


def _background_mask(tree, scene: bpy.types.Scene, mask_layer: Optional[str]):
    """(the picture's Render Layers node, the background mask socket: 1 where relevancy is low)."""
    nodes, links = tree.nodes, tree.links
    layers = nodes.new("CompositorNodeRLayers")
    layers.scene = scene
    layers.location = (-600, 0)
    mask_layers = layers
    if mask_layer is not None:
        layers.layer = next(v.name for v in scene.view_layers if v.name != mask_layer)
        mask_layers = nodes.new("CompositorNodeRLayers")
        mask_layers.scene, mask_layers.layer = scene, mask_layer
        mask_layers.location = (-600, -300)
    if RELEVANCY_PASS not in mask_layers.outputs:
        raise RuntimeError("the render engine does not provide a Relevancy pass: set the scene's render "
                           "engine to '4-LEGS Splats' before building the compositor")
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
    links.new(mask_layers.outputs[RELEVANCY_PASS], mask.inputs[0])
    links.new(mask.outputs[0], invert.inputs[1])
    mask.location, invert.location = (-400, -250), (-200, -250)
    return layers, invert.outputs[0]


def _weighted_mix(tree, image, changed, background, weight_name: str, x: float):
    """Mix ``image`` toward ``changed`` by background × a keyed Value node named ``weight_name``; returns
    (the mix's output socket, the Value node)."""
    nodes, links = tree.nodes, tree.links
    weight = nodes.new(VALUE_NODE)
    weight.name = weight.label = weight_name
    weight.outputs[0].default_value = 0.0
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
    links.new(image, mix_a)
    links.new(changed, mix_b)
    links.new(background, scale.inputs[0])
    links.new(weight.outputs[0], scale.inputs[1])
    links.new(scale.outputs[0], mix_f)
    weight.location, scale.location, mix.location = (x - 200, -450), (x, -300), (x + 200, 0)
    return mix_out, weight


def _key(tree, data_path: str, index: int, weights: dict[int, float], scale: float) -> None:
    """Key ``data_path[index]`` of the tree on every frame of ``weights`` (value: weight × ``scale``), in the
    tree's one action (created, tagged, on first use)."""
    from .keyframes import ensure_action

    frames = sorted(weights)
    write_fcurve(tree, ensure_action(tree, "4-LEGS Compositor"), data_path, index, frames,
                 [weights[f] * scale for f in frames], ["LINEAR"] * len(frames))


def _blur_branch(tree, scene: bpy.types.Scene, plan: dict[str, Any], image, background):
    """The background blurred: a Gaussian blur whose size (pixels) is keyed to weight × radius × height."""
    blur = tree.nodes.new("CompositorNodeBlur")
    blur.name = blur.label = BLUR_NODE
    blur.location = (-100, 200)
    tree.links.new(image, blur.inputs["Image"])
    out, weight = _weighted_mix(tree, image, blur.outputs["Image"], background, BLUR_WEIGHT_NODE, 100)
    weights = frame_weights(plan, "blur")
    height = float(plan["resolution"][1]) * scene.render.resolution_percentage / 100.0
    pixels = float(plan["blur"].get("radius", 0.02)) * height
    _key(tree, f'nodes["{BLUR_WEIGHT_NODE}"].outputs[0].default_value', 0, weights, 1.0)
    if IS_50:
        for index in (0, 1):
            _key(tree, f'nodes["{BLUR_NODE}"].inputs[1].default_value', index, weights, pixels)
    else:  # 4.x: the size is a property, the keyed "Size" input scales it
        blur.filter_type = "GAUSS"
        blur.size_x = blur.size_y = max(1, int(round(pixels)))
        _key(tree, 'nodes["Background Blur"].inputs[1].default_value', 0, weights, 1.0)
    return out


def _desaturation_branch(tree, plan: dict[str, Any], image, background):
    """The background greyed: Hue/Saturation at saturation 0, mixed in by the keyed desaturation weight."""
    gray = tree.nodes.new("CompositorNodeHueSat")
    gray.inputs["Saturation"].default_value = 0.0
    gray.location = (350, 200)
    tree.links.new(image, gray.inputs["Image"])
    out, _ = _weighted_mix(tree, image, gray.outputs["Image"], background, WEIGHT_NODE, 550)
    _key(tree, f'nodes["{WEIGHT_NODE}"].outputs[0].default_value', 0, frame_weights(plan), 1.0)
    return out


def build_compositor(scene: bpy.types.Scene, plan: dict[str, Any], mask_layer: Optional[str] = None):
    """Create the blur/desaturation graph if ``plan`` has either; otherwise remove ours. Returns the tree or None.

    The Relevancy pass comes from the picture's own view layer (the 4-LEGS Splats engine declares it
    when ``view_layer.fourlegs_relevancy`` is set, see ``render_engine``) or, with ``mask_layer``, from
    that view layer's AOV (EEVEE and Cycles, see ``native_render``).
    """
    remove_compositor(scene)
    if not (plan.get("desaturate") or plan.get("blur")):
        return None
    tree, out_socket = _new_tree(scene)
    layers, background = _background_mask(tree, scene, mask_layer)
    image = layers.outputs["Image"]
    if plan.get("blur"):
        image = _blur_branch(tree, scene, plan, image, background)
    if plan.get("desaturate"):
        image = _desaturation_branch(tree, plan, image, background)
    tree.links.new(image, out_socket)
    scene.render.use_compositing = True
    return tree
