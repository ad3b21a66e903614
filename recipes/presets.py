"""Presets against each other: the two-surface model at each size preset, trained alike over seeds.

Usage: ``python -m recipes.presets --out OUT [--quick] [--seeds N] [--presets realtime,small,paper]
[--saturation-weight W] [--subject DIR | --shards DIR]``.

Every preset is trained with the ablations' budget (L1 only, the same capture, iterations and seeds;
default 5 seeds here, since one stalled seed in five is what this recipe has to show) and evaluated
on the held-out cameras, in foreground metrics (PSNR/SSIM/FLIP inside the person's padded mask box;
the official protocol's numbers beside them). The claim of the ``realtime`` preset is tested paired
by seed: realtime >= small - 0.5 dB foreground PSNR. ``--saturation-weight 0`` trains without the
penalty on U-Net logits (``TrainConfig.saturation_weight``), to see what it does. Frame rates are
machine-dependent and come from ``make bench`` (docs/performance.md); the ms per frame in the tables
is ``deliffas eval``'s plain-path stage timing at the capture's size.
"""

from __future__ import annotations

import dataclasses

from recipes.common import (ablation_sizes, prepare_capture, prepare_shards, recipe_parser, seed_list,
                            train_and_eval_seeds, write_outputs)
from recipes.seeds import ordering

MODEL = "two_surface"
DEFAULT_PRESETS = ("realtime", "small")
"""The presets trained by default (``paper`` takes about 25 min per seed on 2 cores: ask for it)."""
DEFAULT_SEEDS = 5
REALTIME_MARGIN_DB = -0.5
"""The real-time preset's claim: foreground PSNR at least small's minus 0.5 dB."""


def parse_presets(text: str | None) -> list[str]:
    """``--presets``: zoo presets of the two-surface model, in the order given (default realtime, small)."""
    from deliffas.models.zoo import list_presets

    if text is None:
        return list(DEFAULT_PRESETS)
    known = list_presets(MODEL)
    wanted = [t.strip() for t in text.split(",") if t.strip()]
    if not wanted or any(w not in known for w in wanted) or len(set(wanted)) != len(wanted):
        raise ValueError(f"--presets: expected distinct names from {','.join(known)}, got {text!r}")
    return wanted


def main(argv=None) -> dict:
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--presets", default=None,
                   help=f"comma-separated presets of {MODEL} (default {','.join(DEFAULT_PRESETS)})")
    p.add_argument("--saturation-weight", type=float, default=None,
                   help="TrainConfig.saturation_weight of every run (default: the TrainConfig default; 0 = off)")
    args = p.parse_args(argv)
    try:
        presets = parse_presets(args.presets)
    except ValueError as exc:
        p.error(str(exc))
    if args.saturation_weight is not None and not args.saturation_weight >= 0:
        p.error(f"--saturation-weight must be >= 0, got {args.saturation_weight}")
    if args.seeds is None and not args.quick:
        args.seeds = DEFAULT_SEEDS
    sizes = ablation_sizes(args)
    seeds = seed_list(args)
    jobs = 1 if args.quick else 2
    shards = args.shards or prepare_shards(args.out, prepare_capture(args.out, sizes, 0, args.subject, jobs=jobs),
                                           sizes, jobs=jobs)
    train_kw = {} if args.saturation_weight is None else {"saturation_weight": args.saturation_weight}
    rows = [train_and_eval_seeds(preset, shards, args.out / "runs" / preset, sizes, MODEL, seeds, args.device,
                                 extra_splits=False, preset=preset, **train_kw)
            for preset in presets]
    by = dict(zip(presets, rows))
    claims, lines = {}, []
    if "realtime" in by and "small" in by:
        claim = ordering(f"realtime >= small {REALTIME_MARGIN_DB:+.1f} dB (fg PSNR)", by["realtime"], by["small"],
                         "fg_psnr", REALTIME_MARGIN_DB)
        lines.append(f"- {claim.sentence()}")
        claims["realtime_within_0.5_db_of_small"] = claim.to_dict()
    from deliffas.engine.train_config import TrainConfig

    weight = TrainConfig.saturation_weight if args.saturation_weight is None else args.saturation_weight
    notes = ["## The real-time preset's claim", "", *(lines or ["- not tested: train both realtime and small"]), "",
             f"All rows: {MODEL}, L1 only, {sizes.iters} iterations, {sizes.cameras_per_frame} cameras per iteration, "
             f"saturation weight {weight:g}, seeds {seeds}; capture {sizes.frames} frames, {sizes.cameras} cameras "
             f"at {sizes.size}x{sizes.size}.",
             *(["Quick mode: a few iterations; the numbers show the pipeline works, not the claim."]
               if args.quick else [])]
    title = "Presets: accuracy over seeds" + (" — quick mode" if args.quick else "")
    return write_outputs(args.out, title, rows, {"quick": args.quick, "sizes": dataclasses.asdict(sizes),
                                                 "seeds": seeds, "presets": presets, "saturation_weight": weight,
                                                 "claims": claims}, notes)


if __name__ == "__main__":
    main()
