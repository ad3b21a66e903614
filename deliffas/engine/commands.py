"""The engine's CLI commands (``zoo``, ``train``, ``eval``, ``render``, ``demo``): argument parsing only."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from deliffas.engine.memory import retain_freed_memory

__all__ = ["add_engine_commands"]


def _cmd_zoo(args: argparse.Namespace) -> int:
    from deliffas.models.deliffas import DeliffasModel
    from deliffas.models.zoo import get_config, list_models, list_presets

    rows = []
    for name in list_models():
        for preset in list_presets(name):
            cfg = get_config(name, preset)
            params = DeliffasModel(cfg).num_parameters() if preset != "paper" or args.count_paper else None
            rows.append({"model": name, "preset": preset, "atlas_res": cfg.atlas_res,
                         "mlp": f"{cfg.mlp.depth}x{cfg.mlp.width}", "features": cfg.feature_channels,
                         "parameters": params})
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'model':<26} {'preset':<7} {'S':>5} {'mlp':>7} {'feat':>5} {'params':>12}")
    for r in rows:
        p = f"{r['parameters']:,}" if r["parameters"] is not None else "(--count-paper)"
        print(f"{r['model']:<26} {r['preset']:<7} {r['atlas_res']:>5} {r['mlp']:>7} {r['features']:>5} {p:>12}")
    return 0


def _train_config(args: argparse.Namespace):
    from deliffas.engine.train import TrainConfig

    values: dict = {}
    if args.config:
        values.update(json.loads(Path(args.config).read_text()))
    values.update(shards=str(args.shards), out=str(args.out))
    for key in ("model", "preset", "iters", "perceptual", "perceptual_mode", "cameras_per_frame", "device",
                "num_workers", "seed", "vgg16_path", "checkpoint_every", "preview_every", "ray_chunk"):
        v = getattr(args, key, None)
        if v is not None:
            values[key] = v
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise SystemExit(f"deliffas train: unknown config keys {unknown} (known: {sorted(known)})")
    return TrainConfig(**values)


def _cmd_train(args: argparse.Namespace) -> int:
    retain_freed_memory()
    cfg = _train_config(args)
    if args.auto_capacity:
        from deliffas.engine.auto_capacity import AutoCapacityConfig, auto_capacity

        result = auto_capacity(cfg, AutoCapacityConfig(tolerance_db=args.tolerance_db))
        print(json.dumps(result, indent=2))
        return 0
    from deliffas.engine.train import train

    result = train(cfg, resume=args.resume)
    print(f"trained {cfg.model} ({cfg.preset}) for {result.iterations} iterations in {result.seconds:.0f} s "
          f"({result.iters_per_second:.2f} it/s); run in {result.run_dir}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    retain_freed_memory()
    from deliffas.engine.evaluate import EvalConfig, evaluate

    result = evaluate(EvalConfig(run=str(args.run), split=args.split, shards=args.shards, max_frames=args.max_frames,
                                 device=args.device, save_images=args.save_images, vgg16_path=args.vgg16_path,
                                 lpips_path=args.lpips_path))
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.split}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, "
              f"LPIPS {result['lpips'] if result['lpips'] is not None else 'n/a (' + result['lpips_reason'] + ')'}, "
              f"{result['fps']:.2f} fps; stage ms " + ", ".join(f"{k} {v:.1f}" for k, v in result["stage_ms"].items()))
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    retain_freed_memory()
    from deliffas.engine.render import RenderConfig, render_video

    out = render_video(RenderConfig(run=str(args.run), out=str(args.out), orbit=args.orbit,
                                    motion=str(args.motion) if args.motion else None, frames=args.frames,
                                    size=args.size, device=args.device, fps=args.fps))
    print(f"wrote {out}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    retain_freed_memory()
    from deliffas.engine.demo import DemoConfig, run_demo

    report = run_demo(DemoConfig(out=str(args.out), quick=args.quick))
    print(f"demo report: {report}")
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 256x256, got {text!r}") from None


def add_engine_commands(sub) -> None:
    """Add the engine's subcommands to the ``deliffas`` parser."""
    p = sub.add_parser("zoo", help="list the model zoo (named configurations and presets)")
    p.add_argument("action", choices=["list"], help="what to do")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--count-paper", action="store_true", help="also build the paper-size models to count parameters")
    p.set_defaults(func=_cmd_zoo)

    p = sub.add_parser("train", help="train a model of the zoo on converted shards",
                       description="Train on SHARDS (from `deliffas convert`). L1 first, then L1 + perceptual "
                                   "when --perceptual is given. Distributed with `torchrun --nproc_per_node N -m deliffas train ...`.")
    p.add_argument("shards", type=Path)
    p.add_argument("--model", default=None, help="zoo name (default two_surface)")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--preset", default=None, help="paper | small (default) | tiny")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--config", type=Path, default=None, help="JSON file of TrainConfig fields (incl. model_overrides)")
    p.add_argument("--resume", action="store_true", help="continue from the run directory's last checkpoint")
    p.add_argument("--perceptual", choices=["none", "vgg16-imagenet", "vgg16-random"], default=None,
                   help="stage-2 perceptual backbone; vgg16-random is the explicit offline option")
    p.add_argument("--perceptual-mode", choices=["image", "patch"], default=None)
    p.add_argument("--vgg16-path", default=None, help="ImageNet VGG-16 weights (.pth/.safetensors)")
    p.add_argument("--cameras-per-frame", type=int, default=None)
    p.add_argument("--device", default=None, help="cpu | cuda | cuda:N")
    p.add_argument("--workers", dest="num_workers", type=int, default=None, help="DataLoader workers")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--ray-chunk", type=int, default=None,
                   help="rays per backward pass (bounds training memory; single process)")
    p.add_argument("--checkpoint-every", type=int, default=None)
    p.add_argument("--preview-every", type=int, default=None)
    p.add_argument("--auto-capacity", action="store_true",
                   help="search model capacities and keep the cheapest within --tolerance-db of the best")
    p.add_argument("--tolerance-db", type=float, default=0.5)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help="evaluate a run: PSNR/SSIM (+LPIPS when weights exist) and per-stage timing")
    p.add_argument("run", type=Path)
    p.add_argument("--split", choices=["novel_view", "novel_pose", "train"], default="novel_view")
    p.add_argument("--shards", default=None, help="shard directory (default: the run's)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--device", default="cpu")
    p.add_argument("--save-images", default=None, help="folder for predicted images (white background)")
    p.add_argument("--vgg16-path", default=None)
    p.add_argument("--lpips-path", default=None)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("render", help="free-viewpoint video of a trained avatar driven by a motion")
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, required=True, help="video file (.mp4 or .avi)")
    p.add_argument("--orbit", action="store_true", help="camera orbits the avatar (default: capture camera 0)")
    p.add_argument("--motion", type=Path, default=None, help=".motion file (default: the capture's test motion)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: all of the motion, max 300)")
    p.add_argument("--size", type=_size, default=None, help="WxH (default: the capture's)")
    p.add_argument("--fps", type=float, default=25.0)
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("demo", help="the whole path on the embedded procedural character, with a report")
    p.add_argument("--out", type=Path, default=Path("demo_out"))
    p.add_argument("--quick", action="store_true", help="a smaller run (used by tests)")
    p.set_defaults(func=_cmd_demo)
