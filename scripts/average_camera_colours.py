"""Copy a bundle fitted before `fourlegs fit` expressed colours in the average training camera's response,
applying that transform (fourlegs_engine.fit.model.average_camera_colours) on the way.

    python scripts/average_camera_colours.py FITTED_BUNDLE OUT_BUNDLE
"""
from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

from fourlegs_engine.errors import InputError
from fourlegs_engine.fit.model import average_camera_colours
from fourlegs_engine.scene.bundle import load_bundle, write_bundle


def main(src: str, dst: str) -> int:
    scene = load_bundle(src)
    correction = scene.metadata.get("color_correction")
    if not correction or "cam_m" not in correction or "cam_c" not in correction:
        raise InputError("no colour correction in metadata (not a fitted bundle)", file=src, field="color_correction")
    colors, cam_m, cam_c = average_camera_colours(np.asarray(scene.gaussians.colors), correction["cam_m"],
                                                  correction["cam_c"])
    metadata = {**scene.metadata, "color_correction": {"cam_m": cam_m.tolist(), "cam_c": cam_c.tolist()}}
    write_bundle(replace(scene, gaussians=replace(scene.gaussians, colors=colors), metadata=metadata), dst)
    print(f"wrote {dst}: colour gain {np.exp(np.mean(correction['cam_m'], 0)).round(4).tolist()}, "
          f"offset {np.mean(correction['cam_c'], 0).round(4).tolist()} moved into the colours")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2]))
