"""The ``deliffas`` command line: a thin layer of argument parsing over the Python API."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

__all__ = ["main", "build_parser"]


def _cmd_pose(args: argparse.Namespace) -> int:
    from deliffas.geometry.posing import pose_frames, write_posed_mesh

    verts, character = pose_frames(args.character, args.motion, [args.frame], args.skinning)
    write_posed_mesh(args.out, verts[0], character)
    print(f"wrote {args.out}: {verts.shape[1]} vertices, {character.mesh.num_faces} faces "
          f"(frame {args.frame}, {args.skinning})")
    return 0


# --------------------------------------------------------------------------------------------- data commands
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 256x256, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"image size must be positive, got {text!r}")
    return w, h


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _test_cameras(text: str) -> int | tuple[int, ...]:
    """``N`` (a count) or a list ``a,b,...`` (``3,`` names camera 3 alone)."""
    if "," in text or "[" in text:
        return _int_list(text.strip("[]"))
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a count N or a list a,b,..., got {text!r}") from None


def _cmd_synth(args: argparse.Namespace) -> int:
    from deliffas.data.synth import SynthConfig, synthesize_capture

    w, h = args.size
    cfg = SynthConfig(num_frames=args.frames, num_test_frames=args.test_frames, num_cameras=args.cameras,
                      width=w, height=h, test_cameras=args.test_cameras, seed=args.seed,
                      character=str(args.character) if args.character else None,
                      motion=str(args.motion) if args.motion else None, videos=args.videos, jobs=args.jobs,
                      supersample=args.supersample)
    res = synthesize_capture(args.out_dir, cfg)
    n = sum(len(f) for f in res.frames.values())
    print(f"wrote {res.out_dir}: {len(res.cameras)} cameras (test {res.test_cameras}), "
          f"{len(res.frames['training'])} training + {len(res.frames['testing'])} testing frames at {w}x{h} "
          f"in {res.seconds['total']:.1f} s ({res.seconds['render'] / max(n, 1):.2f} s/frame rendering)")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from deliffas.data.convert import ConvertConfig, convert

    cfg = ConvertConfig(frames=args.frames, cameras=args.cameras, shard_frames=args.shard_frames, jobs=args.jobs,
                        resume=args.resume, overwrite=args.overwrite, meshes=tuple(args.meshes or ()),
                        template=str(args.template) if args.template else None, atlas_res=args.atlas_res,
                        offset_mm=args.offset, codec=args.codec, window=args.window, layout=args.layout,
                        test_cameras=args.test_cameras, masks=args.masks, progress=not args.no_progress)
    try:
        res = convert(args.subject, args.out, cfg)
    except (FileExistsError, ValueError) as err:
        print(f"deliffas convert: error: {err}", file=sys.stderr)
        return 2
    work = res.seconds - res.seconds_setup
    rate = res.frames_converted / work if work > 0 else 0.0
    print(f"wrote {res.out_dir}: {res.shards_total} shards ({res.shards_skipped} kept from before), "
          f"{res.frames_converted} frames / {res.images_converted} images in {res.seconds:.1f} s "
          f"(setup {res.seconds_setup:.1f} s, then {rate:.2f} frames/s), {res.bytes_total / 1e6:.1f} MB")
    return 0


def _cmd_verify(args: argparse.Namespace) -> int:
    from deliffas.data.shards import verify_shards

    problems = verify_shards(args.out, deep=not args.quick)
    for p in problems:
        print(f"BROKEN {p}", file=sys.stderr)
    if problems:
        print(f"deliffas verify: {len(problems)} problem(s) in {args.out}", file=sys.stderr)
        return 1
    print(f"{args.out}: every shard matches the manifest")
    return 0


def _cmd_cameras(args: argparse.Namespace) -> int:
    from deliffas.io.colmap import calibration_from_colmap, calibration_to_colmap

    if args.to_colmap:
        n = calibration_to_colmap(args.calibration, args.to_colmap, text=args.text)
        print(f"wrote a COLMAP model of {n} cameras to {args.to_colmap}")
    else:
        n = calibration_from_colmap(args.from_colmap, args.calibration)
        print(f"wrote {args.calibration} with {n} cameras from {args.from_colmap}")
    return 0


def _add_data_commands(sub) -> None:
    p = sub.add_parser("synth", help="render a synthetic DynaCap capture with a loose garment",
                       description="Write a synthetic subject folder in DynaCap layout (cameras, character, "
                                   "training + novel-pose motions, RGBA images, optional videos, ground-truth "
                                   ".meshes). See docs/data.md.")
    p.add_argument("out_dir", type=Path, help="subject folder to write")
    p.add_argument("--character", type=Path, help=".character to use (default: the procedural character, "
                                                  "built into OUT_DIR/character)")
    p.add_argument("--motion", type=Path, help="training .motion (default: procedural motion)")
    p.add_argument("--frames", type=int, default=20, help="training frames (default 20)")
    p.add_argument("--test-frames", type=int, default=None, help="novel-pose frames (default frames // 2)")
    p.add_argument("--cameras", type=int, default=8, help="cameras of the dome (default 8)")
    p.add_argument("--size", type=_size, default=(256, 256), help="image size WxH (default 256x256)")
    p.add_argument("--test-cameras", type=_test_cameras, default=None,
                   help="held-out cameras: a count N or a list a,b,... (default max(1, cameras // 8))")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--videos", action="store_true", help="also write FFV1 videos img/c_<cam>.avi + fg/c_<cam>.avi")
    p.add_argument("--supersample", type=int, default=1, help="s x s rays per pixel (default 1)")
    p.add_argument("--jobs", type=int, default=1, help="rendering processes (default 1)")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("convert", help="convert a DynaCap subject into sharded HDF5",
                       description="Convert SUBJECT (image folders or videos) into HDF5 shards + meta.h5 + "
                                   "manifest.json under OUT (schema: docs/shards.md). SUBJECT is only read.")
    p.add_argument("subject", type=Path, help="subject folder (cameras.calibration, character/, training/, testing/)")
    p.add_argument("out", type=Path, help="output folder")
    p.add_argument("--frames", default=None, help="A:B:STEP capture frames (default: all)")
    p.add_argument("--cameras", type=_int_list, default=None, help="calibration indices a,b,... (default: all)")
    p.add_argument("--test-cameras", type=_int_list, default=None,
                   help="held-out cameras a,b,... (default: SUBJECT/split.json or test_cameras.txt)")
    p.add_argument("--shard-frames", type=int, default=10, help="frames per shard (default 10)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--resume", action="store_true", help="keep complete shards of an interrupted run")
    p.add_argument("--overwrite", action="store_true", help="replace an existing conversion in OUT")
    p.add_argument("--meshes", action="append", metavar="[SEQ=]FILE",
                   help="tracked .meshes instead of the skinned template (SEQ default training; repeatable)")
    p.add_argument("--template", type=Path, help="template variant folder (its .character + outer.obj)")
    p.add_argument("--atlas-res", type=int, default=256, help="normal-map side S (default 256; paper 1024)")
    p.add_argument("--offset", type=float, default=30.0, help="outer-surface offset d in mm (default 30)")
    p.add_argument("--window", type=int, default=2, help="temporal window T stored per frame (default 2)")
    p.add_argument("--codec", default="raw", help="raw (lossless, default) | png | jpeg:Q")
    p.add_argument("--layout", choices=["auto", "images", "videos"], default="auto", help="frame layout")
    p.add_argument("--masks", metavar="SUBDIR", help="DDC mask folder in each sequence folder "
                                                     "(<cam>/image_c_<cam>_f_<frame>.png|jpg) replacing alpha/fg")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser("verify", help="check converted shards against their manifest",
                       description="Check every shard of OUT against manifest.json (presence, size, sha256, "
                                   "readability, completeness); exit 1 naming each broken shard.")
    p.add_argument("out", type=Path, help="folder written by 'deliffas convert'")
    p.add_argument("--quick", action="store_true", help="checksums only, do not read every dataset")
    p.set_defaults(func=_cmd_verify)

    p = sub.add_parser("cameras", help="convert a cameras.calibration to or from a COLMAP model",
                       description="COLMAP's pixel convention equals DynaCap's (pixel centres at +0.5): "
                                   "intrinsics are copied unchanged (docs/data.md).")
    p.add_argument("calibration", type=Path, help="cameras.calibration (read with --to-colmap, written with --from-colmap)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--to-colmap", type=Path, metavar="DIR", help="write cameras/images/points3D to DIR")
    g.add_argument("--from-colmap", type=Path, metavar="DIR", help="read a COLMAP model from DIR")
    p.add_argument("--text", action="store_true", help="write the .txt model instead of .bin")
    p.set_defaults(func=_cmd_cameras)


# --------------------------------------------------------------------------------------------- geometry commands
def _cmd_character_procedural(args: argparse.Namespace) -> int:
    from deliffas.io.dynacap import read_character
    from deliffas.geometry.procedural import make_procedural_character

    try:
        path = make_procedural_character(args.out_dir, seed=args.seed, target_faces=args.faces, name=args.name,
                                         texture_size=args.texture_size)
    except ValueError as err:
        print(f"deliffas character procedural: error: {err}", file=sys.stderr)
        return 2
    c = read_character(path)
    print(f"wrote {path}: {c.mesh.num_verts} vertices, {c.mesh.num_faces} faces, {c.skeleton.num_dofs} DOFs, "
          f"{c.graph.num_verts if c.graph is not None else 0} graph nodes, height {c.mesh.verts[:, 1].max():.0f} mm")
    return 0


def _cmd_template(args: argparse.Namespace) -> int:
    from deliffas.data.template_build import build_templates

    try:
        report = build_templates(args.character, args.out, smooth_iters=args.smooth, coarse_faces=args.coarse,
                                 offset_mm=args.offset, safe=args.safe, atlas_res=args.atlas_res)
    except ValueError as err:  # bad arguments or files (DynaCapFormatError is a ValueError)
        print(f"deliffas template: error: {err}", file=sys.stderr)
        return 2
    for name, v in report["variants"].items():
        sh = v["shell"]
        print(f"{name:>8}: {v['num_verts']} vertices, {v['num_faces']} faces, watertight {v['watertight']}, "
              f"shell self-intersecting faces {sh['num_self_intersecting_faces']}"
              + (f", {sh['num_clamped']} offsets clamped" if args.safe else ""))
    print(f"wrote {args.out}/{{{','.join(report['variants'])}}}/ and {args.out}/report.json")
    return 0


def _add_geometry_commands(sub) -> None:
    p = sub.add_parser("character", help="build characters (subcommand: procedural)",
                       description="Build DynaCap characters.")
    csub = p.add_subparsers(dest="character_command", required=True, metavar="KIND")
    q = csub.add_parser("procedural", help="write the license-free procedural character",
                        description="Build the procedural human (watertight template, Skeletool skeleton with "
                                    "DDC DOF names, skin, UVs, texture, segmentation with a skirt, embedded "
                                    "graph) and write it as a DynaCap character into OUT_DIR.")
    q.add_argument("out_dir", type=Path, help="folder to write (created)")
    q.add_argument("--seed", type=int, default=0, help="proportions, colours and patterns (default 0)")
    q.add_argument("--faces", type=int, default=8000, help="template face budget (default 8000)")
    q.add_argument("--name", default="procedural", help="file stem (default procedural)")
    q.add_argument("--texture-size", type=int, default=1024, help="texture atlas side in texels (default 1024)")
    q.set_defaults(func=_cmd_character_procedural)

    p = sub.add_parser("template", help="write template variants (original/smooth/coarse) with outer shells",
                       description="Write OUT/<variant>/ (a complete DynaCap character + outer.obj, the offset "
                                   "shell with the same vertex order and UVs) for original and, when asked, "
                                   "smooth and coarse, plus OUT/report.json.")
    p.add_argument("character", type=Path, help=".character file")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--smooth", type=int, metavar="ITERS", help="also a Taubin-smoothed variant (ITERS lambda/mu pairs)")
    p.add_argument("--coarse", type=int, metavar="FACES", help="also a decimated variant with about FACES faces")
    p.add_argument("--offset", type=float, default=30.0, metavar="MM", help="outer-shell offset d in mm (default 30)")
    p.add_argument("--safe", action="store_true", help="limit d per vertex where the shell would cross another part")
    p.add_argument("--atlas-res", type=int, default=512, metavar="R",
                   help="xatlas packing resolution of new atlases and texel grid of the report (default 512)")
    p.set_defaults(func=_cmd_template)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deliffas", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("pose", help="write a DynaCap character posed by one frame of a motion",
                       description="Pose CHARACTER with frame N of MOTION (DOF skeleton + skinning) and "
                                   "write the mesh in the template's vertex order and the files' units (mm).")
    p.add_argument("character", type=Path, help=".character file")
    p.add_argument("motion", type=Path, help=".motion file (its DOF count must match the skeleton)")
    p.add_argument("--frame", type=int, default=0, help="frame index as written in the motion file (default 0)")
    p.add_argument("--skinning", choices=["dqs", "lbs"], default="dqs",
                   help="dual-quaternion (the original tools' default) or linear blend skinning")
    p.add_argument("--out", type=Path, required=True, help="output mesh, .ply or .obj (.obj keeps the UVs)")
    p.set_defaults(func=_cmd_pose)
    _add_data_commands(sub)
    _add_geometry_commands(sub)
    from deliffas.engine.commands import add_engine_commands

    add_engine_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    from deliffas.io.text_lines import DynaCapFormatError

    try:
        return int(args.func(args) or 0)
    except (DynaCapFormatError, FileNotFoundError) as err:
        print(f"deliffas {args.command}: error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:
        zoo = sys.modules.get("deliffas.models.zoo")  # a CheckpointError can only come from a loaded zoo
        if zoo is None or not isinstance(err, zoo.CheckpointError):
            raise
        print(f"deliffas {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
