"""What a mask field's autoencoder makes of each phrase: ``python -m fourlegs_bench.ae_directions BUNDLE``.

For a bundle distilled from annotation masks (``fourlegs language --encoder masks``), each phrase's crop
feature at a few mask coverages is encoded and decoded by the bundle's autoencoder and scored (LERF
relevancy against the canonical phrases) for every phrase, before and after; a phrase whose relevancy
falls below 0.5 after the round trip cannot be found in the lifted field, however good its masks are.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

COVERAGES = (0.34, 1.0)


def round_trip_relevancy(bundle: str | Path, coverages: tuple[float, ...] = COVERAGES) -> list[dict[str, Any]]:
    """Rows {phrase, coverage, cosine (round trip), before: {phrase: R}, after: {phrase: R}}."""
    import torch

    from fourlegs_engine.fileio import read_json
    from fourlegs_engine.language.annotations import AnnotationMaskEncoder
    from fourlegs_engine.language.autoencoder import AE_REPORT, DECODER_FILE, ENCODER_FILE, load_decoder, load_encoder
    from fourlegs_engine.language.phrases import CANONICAL_PHRASES
    from fourlegs_engine.query.lerf import relevancy_reference

    root = Path(bundle)
    config = read_json(root / "features" / "manifest.json")["config"]["encoder_config"]
    encoder = AnnotationMaskEncoder(config["masks"], salience=config.get("salience", 6.0))
    phrases = list(config["masks"])
    enc, dec = load_encoder(root / ENCODER_FILE), load_decoder(root / DECODER_FILE)
    texts = encoder.encode_text(phrases).double().numpy()
    canon = encoder.encode_text(list(CANONICAL_PHRASES)).double().numpy()
    rows = []
    for k, phrase in enumerate(phrases):
        for share in coverages:
            cov = torch.zeros(1, 8, len(phrases), dtype=torch.float64)
            cov[..., k] = share
            feature = encoder.encode_coverage(cov)
            with torch.no_grad():
                back = dec(enc(feature))
            back = back / back.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            score = {p: (float(relevancy_reference(feature.double().numpy(), q, canon)[0]),
                         float(relevancy_reference(back.double().numpy(), q, canon)[0])) for p, q in zip(phrases, texts)}
            rows.append({"phrase": phrase, "coverage": share, "cosine": float((back * feature).sum()),
                         "before": {p: v[0] for p, v in score.items()}, "after": {p: v[1] for p, v in score.items()}})
    report = read_json(root / AE_REPORT) if (root / AE_REPORT).is_file() else {}
    for row in rows:
        row["balance"] = report.get("balance", "none")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bundle", help="bundle with mask features and a trained autoencoder")
    args = parser.parse_args(argv)
    for row in round_trip_relevancy(args.bundle):
        own = row["phrase"]
        best = max(row["after"], key=row["after"].get)
        print(f"{own!r} at {row['coverage']:.0%}: round-trip cosine {row['cosine']:.3f}; relevancy "
              f"{row['before'][own]:.3f} -> {row['after'][own]:.3f}; decoded as {best!r} ({row['after'][best]:.3f}); "
              f"autoencoder sample {row['balance']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
