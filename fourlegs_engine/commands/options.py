"""Command-line options shared by several commands, and their translation into the library's option types.

argparse stays here, at the edge: the library takes :class:`~fourlegs_engine.pipeline.EncoderOptions`,
:class:`~fourlegs_engine.query.options.QueryOptions` and
:class:`~fourlegs_engine.highlight_job.HighlightJobOptions`.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable, Optional

from .. import demo  # noqa: F401 (registers the demo scenes' "simulated" encoder among the --encoder choices)
from ..cluster.runner import DEFAULT_RETRIES, INSTALL_HINT, RayOptions
from ..errors import InputError
from ..highlight_job import DEFAULT_QUERY_PATH, DEFAULT_SPATIAL, VIDEO_FORMATS, HighlightJobOptions
from ..language.encoders import DTYPES, encoder_names
from ..pipeline import EncoderOptions
from ..query.options import QUERY_PATHS
from ..validate import check_number


def bounded(kind: type, low: float | None = None, high: float | None = None, *,
            low_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type=`` that parses ``kind`` (int or float) and enforces the range.

    >>> bounded(float, 0, 8, low_open=True)("2.5")
    2.5
    """
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        try:
            check_number(value, "", low=low, high=high, low_open=low_open, integer=kind is int)
        except InputError as exc:
            raise argparse.ArgumentTypeError(exc.problem) from None
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def add_encoder_arguments(parser: argparse.ArgumentParser, *, default: str = "viclip") -> None:
    """The encoder options shared by every command that encodes video or text."""
    group = parser.add_argument_group("encoder")
    group.add_argument("--encoder", default=default, choices=encoder_names(),
                       help=f"teacher of the language field: a video-text encoder, or 'masks' (per-pixel "
                            f"annotation masks, no network; see --masks) (default: {default})")
    group.add_argument("--masks", action="append", default=None, metavar="PHRASE=FOLDER",
                       help="annotation masks for --encoder masks: FOLDER/{camera}/{t:06d}.png, any nonzero "
                            "pixel set (repeat for several phrases; a later query reuses the recorded ones)")
    group.add_argument("--checkpoint", default=None,
                       help="ViCLIP weights: ViClip-InternVid-10M-FLT.pth, a .safetensors file or a "
                            "ViCLIP-*-hf directory (never downloaded)")
    group.add_argument("--vocab", default=None, help="CLIP BPE vocabulary bpe_simple_vocab_16e6.txt.gz")
    group.add_argument("--viclip-size", default="auto", choices=("auto", "l", "b"),
                       help="ViCLIP size; 'auto' reads it off the checkpoint (default)")
    group.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 or auto (default)")
    group.add_argument("--encoder-dtype", default="float32", choices=sorted(DTYPES),
                       help="ViCLIP weights precision (float16/bfloat16 only on GPU; default float32)")
    group.add_argument("--encoder-batch-size", type=bounded(int, 1, 4096), default=16,
                       help="clips or texts per encoder forward pass (default 16)")
    group.add_argument("--pixel-normalization", default="clip", choices=("clip", "imagenet"),
                       help="pixel statistics ViCLIP sees: 'clip' (as the 4-LEGS pipeline describes, "
                            "default) or 'imagenet' (the statistics ViCLIP was trained with)")


def encoder_options_from_args(args: argparse.Namespace) -> EncoderOptions:
    """The :class:`EncoderOptions` of the options :func:`add_encoder_arguments` defined (missing ones: defaults)."""
    default = EncoderOptions()
    return EncoderOptions(name=getattr(args, "encoder", None) or default.name,
                         checkpoint=getattr(args, "checkpoint", None), vocab=getattr(args, "vocab", None),
                         size=getattr(args, "viclip_size", None) or default.size,
                         device=getattr(args, "device", None) or default.device,
                         dtype=getattr(args, "encoder_dtype", None) or default.dtype,
                         batch_size=getattr(args, "encoder_batch_size", None) or default.batch_size,
                         normalization=getattr(args, "pixel_normalization", None) or default.normalization,
                         masks=_mask_pairs(getattr(args, "masks", None)))


def _mask_pairs(specs: Optional[list[str]]) -> tuple[tuple[str, str], ...]:
    """``--masks`` values ("PHRASE=FOLDER") -> pairs; one clear line for a bad spec."""
    if not specs:
        return ()
    from ..language.annotations import mask_pairs
    return tuple(mask_pairs(specs))


def parse_resolution(text: Optional[str], field: str = "--resolution", *, even: bool = False) -> Optional[tuple[int, int]]:
    """"WIDTHxHEIGHT" -> (width, height); None stays None. ``even``: both sizes even (H.264)."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"expected WIDTHxHEIGHT, got {text!r}", field=field) from None
    if even and (w <= 0 or h <= 0 or w % 2 or h % 2):
        raise InputError(f"needs positive even sizes (H.264), got {w}x{h}", field=field)
    if w <= 0 or h <= 0:
        raise InputError(f"must be positive, got {text!r}", field=field)
    return w, h


def add_demo_argument(parser: argparse.ArgumentParser) -> None:
    """``--demo``: a flag in every command, the synthetic demo scene instead of a scene path."""
    parser.add_argument("--demo", action="store_true",
                        help="use the synthetic demo scene instead of a scene path (generated on first use)")


def add_effect_arguments(parser: argparse.ArgumentParser) -> None:
    """Which of the preset's shots to keep, alike in every command that plans (``plan``, ``highlight``)."""
    parser.add_argument("--effects", metavar="LIST", default=None,
                        help="keep only the preset's shots with these effects (comma-separated)")
    parser.add_argument("--no-effect", action="append", default=[], metavar="EFFECT",
                        help="leave out the preset's shots with this effect (repeatable)")


def effects_of(args: argparse.Namespace) -> tuple[str, ...]:
    """The ``--effects`` list (empty: every effect)."""
    return tuple(e.strip() for e in (args.effects or "").split(",") if e.strip())


def add_highlight_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the main job (``fourlegs highlight`` and ``python -m fourlegs_addon.headless``)."""
    p = parser
    p.add_argument("scene", nargs="?", default=None,
                   help="scene: bundle dir, params.npz dir, .ply file or dir of .ply files (or --demo)")
    p.add_argument("query", help="what to find, e.g. \"a ball flying in the air\"")
    add_demo_argument(p)
    p.add_argument("--demo-size", default="demo", choices=("tiny", "demo", "bench", "full"),
                   help="size of the synthetic demo scene (default demo: 30k Gaussians, 48 timesteps)")
    p.add_argument("--preset", default="broadcast", help="highlight preset name or .toml file (default broadcast)")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--resolution", default=None,
                   help="output WIDTHxHEIGHT (default: 640x360 for --demo, else the preset's)")
    p.add_argument("--fps", type=bounded(float, 0, 240, low_open=True), default=None,
                   help="output frame rate (default: the preset's)")
    p.add_argument("--render-threads", type=bounded(int, 0, 1024), default=1, metavar="N",
                   help="torch threads for the per-frame rasterization (default 1: small per-frame work, "
                        "extra threads mostly wait; 0 = torch's default)")
    p.add_argument("--format", default="MP4", choices=VIDEO_FORMATS, help="video or image sequence")
    add_effect_arguments(p)
    p.add_argument("--query-path", default=DEFAULT_QUERY_PATH, choices=QUERY_PATHS,
                   help="per-Gaussian relevancy path of the query engine (default %(default)s; see "
                        "`fourlegs bench accuracy-time` for what each costs and scores)")
    p.add_argument("--spatial", default=DEFAULT_SPATIAL, choices=("exact", "fast"),
                   help="relevancy maps for the best view and the action centre: exact (128-channel render, "
                        "per-pixel decode, paper) or fast (1-channel per-Gaussian relevancy render); "
                        "default %(default)s")
    add_encoder_arguments(p, default="auto")


def highlight_job_options(args: argparse.Namespace) -> HighlightJobOptions:
    """The :class:`HighlightJobOptions` of the options :func:`add_highlight_arguments` defined.
    InputError for a malformed ``--resolution``."""
    return HighlightJobOptions(
        query=args.query, output=args.output, scene=args.scene, demo=args.demo_size if args.demo else None,
        preset=args.preset, overwrite=args.overwrite, resolution=parse_resolution(args.resolution, even=True),
        fps=args.fps, format=args.format, effects=effects_of(args), no_effect=tuple(args.no_effect),
        query_path=args.query_path,
        spatial=args.spatial, encoder=encoder_options_from_args(args), render_threads=args.render_threads or None)


# ----------------------------------------------------------------------------------- --ray
class _RayAddress(argparse.Action):
    """``--ray [ADDRESS]``; in ``--ray BUNDLE`` (the optional value swallowed the scene argument) the
    value is a scene bundle, not an address: it becomes the scene and the cluster a local one."""

    def __call__(self, parser: Any, namespace: argparse.Namespace, values: Any, option_string: Any = None) -> None:
        if (values not in (None, "local", "auto") and getattr(namespace, "scene", None) is None
                and (Path(values) / "scene.json").is_file()):
            parser.set_defaults(scene=values)   # the scene positional, matched empty afterwards, takes it
            namespace.scene, values = values, "local"
        setattr(namespace, self.dest, values)


def add_ray_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` and its task options (shared by extract, distill and language)."""
    g = parser.add_argument_group("cluster (Ray; needs " + INSTALL_HINT + ")")
    g.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS", action=_RayAddress,
                   help="run the stage as Ray tasks: on a local cluster (no ADDRESS) or the cluster at "
                        "ADDRESS (auto, HOST:6379, ray://HOST:10001)")
    g.add_argument("--ray-cpus", type=float, default=1.0, help="CPUs each task declares (default 1)")
    g.add_argument("--ray-gpus", type=float, default=None,
                   help="GPUs each task declares (default 1 with a CUDA encoder device, else 0)")
    g.add_argument("--ray-retries", type=int, default=DEFAULT_RETRIES,
                   help=f"retries of a failed task (default {DEFAULT_RETRIES})")
    g.add_argument("--ray-chunk", type=int, default=None,
                   help="timesteps per task (default: distillation 1; extraction 1 with RGB encoders such as "
                        "ViCLIP, one run per worker with label encoders, whose cost is rendering)")
    g.add_argument("--ray-no-shared-fs", action="store_true",
                   help="the bundle is not on a filesystem every node sees: ship inputs and results "
                        "through Ray's object store (the driver writes the files)")


def ray_options_from_args(args: argparse.Namespace) -> RayOptions:
    """The :class:`~fourlegs_engine.cluster.RayOptions` of the options :func:`add_ray_arguments` defined."""
    address = getattr(args, "ray", None)
    return RayOptions(address=None if address in (None, "local") else address, num_cpus=args.ray_cpus,
                      num_gpus=args.ray_gpus, retries=args.ray_retries, shared_fs=not args.ray_no_shared_fs,
                      chunk=args.ray_chunk).check()


def uses_ray(args: argparse.Namespace) -> bool:
    """Whether ``--ray`` was given."""
    return getattr(args, "ray", None) is not None
