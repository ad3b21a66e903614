"""Quality limits: what the capture itself allows a trained run, against what the run reaches.

Usage: ``python -m recipes.quality_limits --out OUT --run RUN [--supersampled-shards SS] [--sides 256,512,1024]
[--frames 10]``.

For the run's validation camera and test cameras (the frames ``deliffas eval`` scores) it writes, in
masked PSNR: the run's own score; the **aliasing ceiling** (``engine.quality_limits.aliasing_ceiling``:
the same capture rendered with supersampling, ``deliffas synth --supersample 3``, scored against the
run's point-sampled one: no model without sub-pixel geometry does better); and the **static texture
oracle** (``engine.quality_limits.texture_oracle``: the mean colour of the training rays per texel of
the run's own uv mapping, at each atlas side, also on the training cameras it was fitted on).
``results.json`` and ``results.md`` in OUT.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="output folder (results.json, results.md)")
    p.add_argument("--run", type=Path, required=True, help="a trained run with a validation camera (--val-cameras)")
    p.add_argument("--supersampled-shards", type=Path, default=None,
                   help="the run's capture rendered with --supersample > 1 and converted (default: no aliasing "
                        "ceiling)")
    p.add_argument("--sides", default="256,512,1024", help="atlas sides of the texture oracle (default 256,512,1024)")
    p.add_argument("--frames", type=int, default=10, help="training frames scored, evenly spaced (default 10)")
    return p


def main(argv: list[str] | None = None) -> dict:
    from deliffas.engine.evaluate import EvalConfig, evaluate
    from deliffas.engine.quality_limits import HELD_OUT, aliasing_ceiling, texture_oracle

    args = _parser().parse_args(argv)
    try:
        sides = tuple(int(s) for s in args.sides.split(","))
    except ValueError:
        raise SystemExit(f"--sides: expected comma-separated whole numbers, got {args.sides!r}") from None
    run_scores = {split: evaluate(EvalConfig(run=str(args.run), split=split, max_frames=args.frames))
                  .foreground.masked_psnr for split in HELD_OUT}
    ceiling = None if args.supersampled_shards is None else aliasing_ceiling(args.run, args.supersampled_shards,
                                                                              args.frames)
    oracle = texture_oracle(args.run, sides, args.frames)
    payload = {"run": str(args.run), "frames": args.frames, "run_masked_psnr": run_scores,
               "aliasing_ceiling": ceiling, "texture_oracle": oracle, "command": " ".join(sys.argv)}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(payload, indent=2) + "\n")
    md = ["# Quality limits", "", "Masked PSNR (dB), training frames.", "",
          "| | training cameras | validation camera | test cameras |", "|---|---:|---:|---:|",
          f"| the run | | {run_scores['validation']:.2f} | {run_scores['novel_view']:.2f} |"]
    if ceiling is not None:
        md.append(f"| aliasing ceiling (supersampled capture) | | {ceiling['validation']['masked_psnr']:.2f} | "
                  f"{ceiling['novel_view']['masked_psnr']:.2f} |")
    md += [f"| static texture oracle, atlas {s}² ({oracle['coverage'][s]:.0%} of texels met) | {oracle['train'][s]:.2f} | "
           f"{oracle['validation'][s]:.2f} | {oracle['novel_view'][s]:.2f} |" for s in sides]
    (args.out / "results.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return payload


if __name__ == "__main__":
    main()
