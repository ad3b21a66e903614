"""The handlers of the ``deliffas`` commands: each turns parsed arguments into one Python API call.

Imported by :func:`deliffas.cli.main` only when a command runs, so ``deliffas --help`` stays light.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
from pathlib import Path

from deliffas.io.camera_formats import CamerasConfig, convert_cameras
from deliffas.io.formats.dynacap.character import read_character
from deliffas.geometry.smpl_surface_fit import SurfaceFitConfig
from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character
from deliffas.data.check import CheckConfig
from deliffas.data.check_report import CheckCaptureConfig, check_capture
from deliffas.data.convert import ConvertConfig, convert
from deliffas.data.ingest import IngestConfig, ingest
from deliffas.data.subjects import SubjectOptions
from deliffas.data.posing import PoseConfig, pose_to_file
from deliffas.data.smpl_capture_fit import FitSmplConfig, fit_smpl_capture
from deliffas.data.shards import VerifyConfig, verify_conversion
from deliffas.data.synth import SynthConfig, synthesize_capture
from deliffas.data.template_build import TemplateConfig, build_templates
from deliffas.engine.avatar import ExportConfig, export_avatar
from deliffas.engine.auto_capacity import AutoCapacityConfig, auto_capacity
from deliffas.engine.data_bridge import resolve_protocol
from deliffas.engine.demo import DemoConfig, run_demo
from deliffas.engine.evaluate import EvalConfig, evaluate
from deliffas.engine.memory import retain_freed_memory
from deliffas.engine.render import RenderConfig, render_video
from deliffas.engine.resume import iterations_done, resumed_config
from deliffas.engine.train import RUN_MARKER, TrainConfig, Trainer
from deliffas.engine.zoo_listing import ZooConfig, zoo_listing
from deliffas.engine.view import SubjectViewConfig, ViewConfig, is_capture, view, view_subject
from deliffas.engine.web import export_web
from deliffas.cli.from_config import config_from_args, given_values, option_names


def cmd_pose(args: argparse.Namespace) -> int:
    cfg = config_from_args(PoseConfig, args)
    m = pose_to_file(cfg)
    print(f"wrote {cfg.out}: {m.num_verts} vertices, {m.num_faces} faces "
          f"(frame {cfg.frame}, {m.kind}{', ' + m.skinning if m.skinning else ''})")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    size = {"width": args.size[0], "height": args.size[1]} if args.size else {}
    cfg = config_from_args(SynthConfig, args, **size)
    res = synthesize_capture(args.out_dir, cfg)
    n = sum(len(f) for f in res.frames.values())
    print(f"wrote {res.out_dir}: {len(res.cameras)} cameras (test {res.test_cameras}), "
          f"{len(res.frames['training'])} training + {len(res.frames['testing'])} testing frames at "
          f"{cfg.width}x{cfg.height} "
          f"in {res.seconds['total']:.1f} s ({res.seconds['render'] / max(n, 1):.2f} s/frame rendering)")
    return 0


def _fmt(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def cmd_ingest(args: argparse.Namespace) -> int:
    res = ingest(config_from_args(IngestConfig, args))
    r = res.report
    cams = ", ".join(f"{c['camera']} IoU {_fmt(c['median_silhouette_iou'], '.2f')}" for c in r["cameras"])
    print(f"wrote {res.out}: {r['frames']['fitted']} of {r['frames']['read']} frames fitted, {len(r['cameras'])} "
          f"cameras (test {', '.join(r['test_cameras'])}); body vs masks: {cams}; keypoint reprojection median "
          f"{_fmt(r['keypoints'].get('median_px'), '.1f')} px; report {res.out / 'ingest_report.json'}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    if args.dask:
        # the scheduler address and dashboard link (deliffas.parallel, INFO); dask's own chatter only with -v
        logging.getLogger("deliffas.parallel").setLevel(logging.INFO)
        if not args.verbose:  # read by dask when it is imported (later, by the executor), here and in workers
            os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    cfg = config_from_args(ConvertConfig, args)
    res = convert(args.subject, args.out, cfg)
    work = res.seconds - res.seconds_setup
    rate = res.frames_converted / work if work > 0 else 0.0
    print(f"wrote {res.out_dir}: {res.shards_total} shards ({res.shards_skipped} kept from before), "
          f"{res.frames_converted} frames / {res.images_converted} images in {res.seconds:.1f} s "
          f"(setup {res.seconds_setup:.1f} s, then {rate:.2f} frames/s), {res.bytes_total / 1e6:.1f} MB")
    return 0


def cmd_fit_smpl(args: argparse.Namespace) -> int:
    fit, out = fit_smpl_capture(config_from_args(FitSmplConfig, args,
                                                 fit=config_from_args(SurfaceFitConfig, args, progress=True)))
    for name, r in fit.residual_mm.items():
        print(f"{name}: {len(r)} frames, mean surface distance {r.mean():.1f} mm (max {r.max():.1f})")
    print(f"wrote {out}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    result, report = check_capture(config_from_args(CheckCaptureConfig, args, check=config_from_args(CheckConfig, args),
                                                    subject_options=config_from_args(SubjectOptions, args)))
    print(f"{'PASS' if result.ok else 'FAIL'}: {result.reason}\nwrote {report}")
    return 0 if result.ok else 1


def cmd_verify(args: argparse.Namespace) -> int:
    cfg = config_from_args(VerifyConfig, args)
    result = verify_conversion(cfg)
    if cfg.json:
        print(json.dumps(result.to_json()))
        return 0 if result.ok else 1
    for p in result.problems:
        print(f"BROKEN {p}", file=sys.stderr)
    if not result.ok:
        print(f"deliffas verify: {len(result.problems)} problem(s) in {cfg.out}", file=sys.stderr)
        return 1
    print(f"{cfg.out}: every shard matches the manifest")
    return 0


def cmd_cameras(args: argparse.Namespace) -> int:
    done = convert_cameras(config_from_args(CamerasConfig, args), names=option_names(CamerasConfig))
    print(f"wrote {done.count} cameras as {done.fmt} to {done.path}")
    return 0


def cmd_character_procedural(args: argparse.Namespace) -> int:
    path = make_procedural_character(config_from_args(ProceduralConfig, args))
    c = read_character(path)
    print(f"wrote {path}: {c.mesh.num_verts} vertices, {c.mesh.num_faces} faces, {c.skeleton.num_dofs} DOFs, "
          f"{c.graph.num_verts if c.graph is not None else 0} graph nodes, height {c.mesh.verts[:, 1].max():.0f} mm")
    return 0


def cmd_template(args: argparse.Namespace) -> int:
    cfg = config_from_args(TemplateConfig, args)
    report = build_templates(cfg)
    for name, v in report["variants"].items():
        sh = v["shell"]
        print(f"{name:>8}: {v['num_verts']} vertices, {v['num_faces']} faces, watertight {v['watertight']}, "
              f"shell self-intersecting faces {sh['num_self_intersecting_faces']}"
              + (f", {sh['num_clamped']} offsets clamped" if cfg.safe else ""))
    print(f"wrote {cfg.out}/{{{','.join(report['variants'])}}}/ and {cfg.out}/report.json")
    return 0


def cmd_zoo(args: argparse.Namespace) -> int:
    cfg = config_from_args(ZooConfig, args)
    listing = zoo_listing(cfg)
    rows, avatars = listing["models"], listing["avatars"]
    if cfg.json:
        print(json.dumps(listing if avatars is not None else rows, indent=2))
        return 0
    width = max([len("model"), *(len(r["model"]) for r in rows)])  # the model column fits the longest name
    print(f"{'model':<{width}} {'preset':<8} {'S':>5} {'mlp':>7} {'feat':>5} {'params':>12}")
    for r in rows:
        p = f"{r['parameters']:,}" if r["parameters"] is not None else "(--count-paper)"
        print(f"{r['model']:<{width}} {r['preset']:<8} {r['atlas_res']:>5} {r['mlp']:>7} {r['features']:>5} {p:>12}")
    if avatars is not None:
        print(f"\navatar files under {cfg.folder}: {len(avatars)}")
        for a in avatars:
            print(f"{a['path']}: " + (f"error: {a['error']}" if a.get("error") else
                                      f"{a['model']} ({a['preset']}), S {a['atlas_res']}, {a['mb']:.1f} MB"))
    return 0


def _train_config(args: argparse.Namespace) -> TrainConfig:
    """--config, then the given options; with --resume of an existing run, the run's config they may change."""
    values: dict = {}
    if args.config:
        values.update(json.loads(Path(args.config).read_text()))
    given = given_values(TrainConfig, args)
    out, shards = given.pop("out"), given.pop("shards", None)  # SHARDS and --out, never --config's
    values = {k: v for k, v in values.items() if k not in ("out", "shards")} | given
    if given.get("time_budget") is not None and "iters" in given:
        raise ValueError("give --iters or --time-budget, not both (a time budget chooses the iterations)")
    if args.resume and (Path(out) / RUN_MARKER).is_file():  # the run's own settings; flags change what may change
        flags = option_names(TrainConfig)
        names = {f.name: flags.get(f.name, f"{f.name} (--config)") for f in dataclasses.fields(TrainConfig)}
        return resumed_config(Path(out), {**values, "shards": shards}, names)
    if shards is None:
        raise ValueError(f"give SHARDS, the folder written by 'deliffas convert' ({out} holds no run to --resume)")
    values.update(shards=shards, out=out)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown config keys {unknown} (known: {sorted(known)})")
    return TrainConfig(**values)


def cmd_train(args: argparse.Namespace) -> int:
    retain_freed_memory()
    cfg = _train_config(args)
    if args.auto_capacity:
        result = auto_capacity(cfg, config_from_args(AutoCapacityConfig, args))
        print(json.dumps(result, indent=2))
        return 0
    done = iterations_done(cfg.out) if args.resume else None
    if done is not None and done >= cfg.iters:
        print(f"{cfg.out}: already at iteration {done} (the run's target is {cfg.iters}); pass --iters N "
              f"(more than {done}) to train further")
        return 0
    trainer = Trainer(cfg, resume=args.resume, overwrite=args.overwrite)  # refuses a taken --out first
    print(resolve_protocol(trainer.shards, cfg.protocol)[1], file=sys.stderr)  # stated before training
    result = trainer.run()
    print(f"trained {cfg.model} ({cfg.preset}) to iteration {result.iterations} in {result.seconds:.0f} s "
          f"({result.iters_per_second:.2f} it/s); run in {result.run_dir}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    retain_freed_memory()
    result = evaluate(config_from_args(EvalConfig, args))
    if args.json:
        print(json.dumps(result.to_json()))
        return 0
    fg, official = result.foreground, result.official

    def na(value, spec, reason):
        return format(value, spec) if value is not None else f"n/a ({reason})"

    print(f"{args.split} ({result.images} images, frames protocol {result.protocol})")
    print(f"  foreground (padded mask box): PSNR {fg.psnr:.2f} dB, SSIM {fg.ssim:.4f}, masked PSNR "
          f"{fg.masked_psnr:.2f} dB, FLIP {na(fg.flip, '.4f', fg.flip_reason)}, "
          f"LPIPS {na(fg.lpips, '.4f', fg.lpips_reason)}")
    print(f"  official (white composite, 600x496 crop): PSNR {official.psnr:.2f} dB, SSIM {official.ssim:.4f}, "
          f"FID {na(official.fid, '.2f', official.fid_reason)}")
    print(f"  {result.fps:.2f} fps; stage ms " + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_ms.items()))
    for warning in result.warnings:
        print(f"  warning: {warning}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    retain_freed_memory()
    out = render_video(config_from_args(RenderConfig, args))
    print(f"wrote {out}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    cfg = config_from_args(ExportConfig, args)
    if cfg.web:
        out = export_web(cfg)
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
        print(f"wrote {out} ({size / 1e6:.1f} MB): a static page that plays {cfg.run}; serve it with "
              f"'python -m http.server' in that folder")
        return 0
    out = export_avatar(cfg)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB): model, template files, atlas and cameras of {cfg.run}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    retain_freed_memory()
    run_demo(config_from_args(DemoConfig, args))  # prints the results and the report's path
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    if is_capture(args.run):
        given = [flag for flag, value in (("--compare", args.compare), ("--motion", args.motion),
                                          ("--shards", args.shards)) if value is not None]
        if given:
            raise ValueError(f"{args.run} is a capture (no train_config.json): {', '.join(given)} apply to a run")
        cfg = config_from_args(SubjectViewConfig, args, subject=args.run)
        view_subject(cfg, ready=lambda: _print_view_address(cfg.host, cfg.port))
        return 0
    if args.format != "auto" or args.template is not None:
        raise ValueError(f"{args.run} is a run: --format and --template apply to a capture folder")
    cfg = config_from_args(ViewConfig, args)
    view(cfg, ready=lambda: _print_view_address(cfg.host, cfg.port))
    return 0


def _print_view_address(host: str, port: int) -> None:
    print(f"deliffas view: open http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port} "
          "(Ctrl+C stops)", flush=True)
