"""Ablation a–d of the paper (L1 only): single-surface, +view direction, +two U-Nets, two-surface.

Usage: ``python -m recipes.ablation_single_surface --out OUT [--quick] [--subject DIR | --shards DIR]``.
"""

from __future__ import annotations

from recipes.common import (prepare_capture, prepare_shards, recipe_parser, sizes_from_args, train_and_eval,
                            write_outputs)

ROWS = (("a. single-surface", "single_surface"),
        ("b. single-surface + view direction", "single_surface_viewdir"),
        ("c. single-surface + two U-Nets", "single_surface_two_unet"),
        ("d. two-surface (DELIFFAS)", "two_surface"))


def main(argv=None) -> dict:
    args = recipe_parser(__doc__.splitlines()[0]).parse_args(argv)
    sizes = sizes_from_args(args)
    shards = args.shards or prepare_shards(args.out, prepare_capture(args.out, sizes, args.seed, args.subject), sizes)
    rows = [train_and_eval(label, shards, args.out / "runs" / model, sizes, model, args.seed, args.device)
            for label, model in ROWS]
    best = max(rows, key=lambda r: r["psnr"])
    two = rows[-1]
    notes = [f"Two-surface beats every single-surface variant in PSNR: "
             f"{'yes' if all(two['psnr'] > r['psnr'] for r in rows[:-1]) else 'no'} (best: {best['name']}).",
             "All rows are trained with L1 only, same iterations and cameras per frame."]
    return write_outputs(args.out, "Ablation: single vs two surfaces (L1)" + (" — quick mode" if args.quick else ""),
                         rows, {"quick": args.quick, "sizes": sizes.__dict__}, notes)


if __name__ == "__main__":
    main()
