"""Why a timestep stride loses accuracy on the synthetic proxy, and which space the latents fill should
interpolate in (``docs/benchmarks_language_cost.md``), read off the rows ``fourlegs bench language-cost``
left in its working folder.

* **label changes**: the share of in-between (Gaussian, timestep) pairs whose ground-truth label differs
  from the nearer encoded timestep's, per stride: what no fill from the encoded timesteps can recover.
* **fill space**: each fill's field against the full extraction's field, as the mean cosine per seen
  Gaussian of the decoded features (the space the query reads) over in-between timesteps: the stored
  latents fill (linear in the latents, re-normalized), decode-interpolate-normalize-encode from the same
  lifted neighbours, and the crop-feature interpolation row.

``python -m fourlegs_bench.latent_fill_check WORK/synthetic [--out FILE.json]``
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from fourlegs_engine.language.skipping import encoded_timesteps, fill_sources

FIELD = "bundle/language/latents.npy"


def label_change_share(labels: np.ndarray, stride: int) -> float:
    """Share of the in-between (Gaussian, timestep) pairs of ``labels`` (T, N) whose label differs from the
    nearer encoded timestep's (the earlier on a tie); 0 when the stride leaves no timestep in between."""
    T = labels.shape[0]
    grid = encoded_timesteps(T, stride)
    changed = [float(np.mean(labels[t] != labels[fill_sources(t, grid, "reuse")[0][0]]))
               for t in range(T) if t not in grid]
    return float(np.mean(changed)) if changed else 0.0


def decode_interpolate_encode(encoder: Any, decoder: Any, before: torch.Tensor, after: torch.Tensor,
                              weight: float) -> torch.Tensor:
    """(N, d) latents: both neighbours decoded (zero latents stay zero features), interpolated with
    ``weight`` on ``after``, re-normalized and encoded back; Gaussians zero in both stay zero."""
    with torch.no_grad():
        fa = decoder(before) * (before.norm(dim=1, keepdim=True) > 0)
        fb = decoder(after) * (after.norm(dim=1, keepdim=True) > 0)
        mix = (1.0 - weight) * fa + weight * fb
        seen = mix.norm(dim=1) > 1e-8
        out = torch.zeros_like(before)
        out[seen] = encoder(torch.nn.functional.normalize(mix[seen], dim=1))
    return out


def decoded_cosine(decoder: Any, latents: torch.Tensor, reference: torch.Tensor) -> float:
    """Mean cosine of the decoded features over the Gaussians both fields saw."""
    seen = (latents.norm(dim=1) > 0) & (reference.norm(dim=1) > 0)
    with torch.no_grad():
        return float(torch.nn.functional.cosine_similarity(decoder(latents[seen]), decoder(reference[seen]),
                                                           dim=1).mean())


def fill_space(work: Path, strides: Sequence[int], every: int = 3) -> dict[str, dict[str, float]]:
    """Per stride: the decoded cosine to the full field of the three fills (rows missing in ``work``: absent)."""
    from fourlegs_engine.language.autoencoder import DECODER_FILE, ENCODER_FILE, load_decoder, load_encoder

    full = np.load(work / "full__paper" / FIELD, mmap_mode="r")
    bundle = work / "full__paper" / "bundle"
    encoder, decoder = load_encoder(bundle / ENCODER_FILE), load_decoder(bundle / DECODER_FILE)
    out: dict[str, dict[str, float]] = {}
    for stride in strides:
        grid = encoded_timesteps(full.shape[0], stride)
        between = [t for t in range(full.shape[0]) if t not in grid][::every]
        rows = {"latents (linear)": work / f"stride_{stride}__latents" / FIELD,
                "crop features (interpolate)": work / f"stride_{stride}__interpolate" / FIELD}
        fields = {k: np.load(p, mmap_mode="r") for k, p in rows.items() if p.is_file()}
        scores: dict[str, list[float]] = {k: [] for k in fields}
        if "latents (linear)" in fields:
            scores["decode-interpolate-encode"] = []
        for t in between:
            ref = torch.from_numpy(np.asarray(full[t], np.float32))
            for name, field in fields.items():
                scores[name].append(decoded_cosine(decoder, torch.from_numpy(np.asarray(field[t], np.float32)), ref))
            if "latents (linear)" in fields:
                (a, wa), (b, wb) = fill_sources(t, grid, "latents")
                lat = fields["latents (linear)"]
                alt = decode_interpolate_encode(encoder, decoder, torch.from_numpy(np.asarray(lat[a], np.float32)),
                                                torch.from_numpy(np.asarray(lat[b], np.float32)), wb)
                scores["decode-interpolate-encode"].append(decoded_cosine(decoder, alt, ref))
        out[str(stride)] = {k: float(np.mean(v)) for k, v in scores.items() if v}
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", help="the synthetic rows' folder of `fourlegs bench language-cost` (WORK/synthetic)")
    p.add_argument("--strides", default="2,4,6,8")
    p.add_argument("--out", default=None, help="also write the result as JSON")
    args = p.parse_args(argv)
    from fourlegs_engine.scene.bundle import load_bundle

    torch.set_num_threads(1)
    work = Path(args.work)
    strides = [int(s) for s in args.strides.split(",")]
    labels = np.asarray(load_bundle(work / "full__paper" / "bundle").gaussians.labels)
    result = {"gaussians_changing_label": float(np.mean((labels != labels[0]).any(0))),
              "label_change_share": {str(s): label_change_share(labels, s) for s in strides},
              "decoded_cosine_to_full": fill_space(work, strides), "work": str(work)}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        from fourlegs_engine.fileio import write_json_atomic
        write_json_atomic(args.out, result, overwrite=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
