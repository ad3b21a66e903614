"""The ``deliffas`` command line: a thin layer of argument parsing over the Python API.

This module only parses (``deliffas --help`` imports no torch); the handlers that call the API are
:mod:`deliffas.cli.handlers`, imported when a command runs. Bad input ends in one ``error:`` line on
stderr and exit code 2 (``-v`` also logs the traceback).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from deliffas import __version__
from deliffas.cli.from_config import add_config_arguments
from deliffas.optional import interrupted_import
from deliffas.options import image_size

__all__ = ["main", "build_parser"]

log = logging.getLogger(__name__)


def _add_plain_option(p: argparse.ArgumentParser) -> None:
    """``--plain`` of render and view: ``fast=None`` instead of the fast path (``cli.fast_env``), not a field."""
    p.add_argument("--plain", action="store_true",
                   help="render as 'deliffas eval' does (ray-cast uvs, fp32 MLP) instead of the CPU fast path "
                        "(rasterised uvs, fused inputs, bf16 MLP where the CPU has native bf16)")


def _add_capture_commands(sub) -> None:
    """synth and convert."""
    p = sub.add_parser("synth", help="render a synthetic DynaCap capture with a loose garment",
                       description="Write a synthetic subject folder in DynaCap layout (cameras, the body: a DDC "
                                   "character or an SMPL model, training + novel-pose motions, RGBA images, "
                                   "optional videos, ground-truth .meshes). See docs/data.md.")
    p.add_argument("out_dir", type=Path, help="subject folder to write")
    from deliffas.data.synth_config import SynthConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, SynthConfig)
    p.add_argument("--size", type=image_size, default=None,  # one option, two fields: SynthConfig.width, height
                   help=f"image size WxH (default {SynthConfig.width}x{SynthConfig.height})")
    p.set_defaults(handler="synth")

    p = sub.add_parser("convert", help="convert a capture into sharded HDF5",
                       description="Convert SUBJECT (image folders or videos) into HDF5 shards + meta.h5 + "
                                   "manifest.json under OUT (schema: docs/shards.md). SUBJECT is only read. "
                                   "The template (DDC character or SMPL model) is recorded in meta.h5.")
    p.add_argument("subject", type=Path, help="subject folder (cameras.calibration, character/ or body/, "
                                              "training/, testing/)")
    p.add_argument("out", type=Path, help="output folder")
    from deliffas.data.convert_config import ConvertConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, ConvertConfig)
    p.set_defaults(handler="convert")


def _add_capture_tool_commands(sub) -> None:
    """ingest, fit-smpl, check, verify and cameras."""
    p = sub.add_parser("ingest", help="turn a raw calibrated multi-view recording (videos + calibration) into a "
                                      "subject with masks and a fitted body per frame",
                       description="Read RECORDING (one video or image folder per camera and a calibration in any "
                                   "format 'deliffas cameras' reads), detect the person in every frame (mask and 2-D "
                                   "keypoints, MediaPipe: pip install 'deliffas[ingest]'), triangulate the keypoints, "
                                   "fit the body model (one shape, a pose per frame) to them and to the masks, and "
                                   "write a DynaCap subject to --out that check, convert and train read unchanged, with "
                                   "ingest_report.json and overlay pictures. See docs/own-recording.md.")
    from deliffas.data.ingest.config import IngestConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, IngestConfig)
    p.set_defaults(handler="ingest")

    p = sub.add_parser("fit-smpl", help="fit SMPL to every frame of a capture (for converting it with SMPL)",
                       description="Fit an SMPL model (one shape, per-frame pose and translation) to the surface "
                                   "of every frame of SUBJECT (its posed template, or tracked .meshes), by "
                                   "symmetric closest-point distance. Writes OUT/<sequence>.npz (AMASS-style, "
                                   "with the capture's frame numbers) and OUT/fit.json (residuals in mm); then "
                                   "`deliffas convert SUBJECT SHARDS --template MODEL --motions training=OUT/"
                                   "training.npz --motions testing=OUT/testing.npz` converts it with SMPL.")
    from deliffas.data.fit_smpl_config import FitSmplConfig  # light; imported here: a Ctrl-C at start-up meets main()
    from deliffas.geometry.smpl_surface_fit_config import SurfaceFitConfig

    add_config_arguments(p, FitSmplConfig)
    add_config_arguments(p, SurfaceFitConfig)
    p.set_defaults(handler="fit_smpl")

    p = sub.add_parser("check", help="score the posed template's silhouette against the masks, per camera",
                       description="Parse SUBJECT, pose its template on a sample of frames, compare its silhouette "
                                   "with every camera's mask (IoU) and name likely causes of failures (pose "
                                   "direction, transposed R, OpenGL axes, m vs mm, frame offset, camera order). "
                                   "Writes OUT/report.md, overlays and summary.json; exit 1 when a camera fails.")
    from deliffas.data.check_capture_config import CheckCaptureConfig  # light; a Ctrl-C at start-up meets main()
    from deliffas.data.check_config import CheckConfig
    from deliffas.data.subject_options import SubjectOptions

    add_config_arguments(p, CheckCaptureConfig)
    add_config_arguments(p, CheckConfig)
    add_config_arguments(p, SubjectOptions)
    p.set_defaults(handler="check")

    p = sub.add_parser("verify", help="check converted shards against their manifest",
                       description="Check every shard of OUT against manifest.json (presence, size, sha256, "
                                   "readability, completeness); exit 1 naming each broken shard.")
    from deliffas.data.verify_config import VerifyConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, VerifyConfig)
    p.set_defaults(handler="verify")

    p = sub.add_parser("cameras", help="convert cameras between capture formats (--help lists them)",
                       description="Read the cameras of SRC (a camera file or a capture folder; format detected "
                                   "unless --from) and write them to OUT in the format --to, converting units, "
                                   "directions, axes and the pixel-centre convention (docs/data.md section 6). "
                                   "Lens distortion the target cannot hold is an error unless --drop-distortion. "
                                   "Shorthands kept from earlier releases: CALIBRATION --to-colmap DIR and "
                                   "CALIBRATION --from-colmap DIR (writes CALIBRATION).")
    from deliffas.io.camera_config import CamerasConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, CamerasConfig)
    p.set_defaults(handler="cameras")


def _add_geometry_commands(sub) -> None:
    p = sub.add_parser("character", help="build characters (subcommand: procedural)",
                       description="Build DynaCap characters.")
    csub = p.add_subparsers(dest="character_command", required=True, metavar="KIND")
    q = csub.add_parser("procedural", help="write the license-free procedural character",
                        description="Build the procedural human (watertight template, Skeletool skeleton with "
                                    "DDC DOF names, skin, UVs, texture, segmentation with a skirt, embedded "
                                    "graph) and write it as a DynaCap character into OUT_DIR.")
    from deliffas.geometry.procedural_config import ProceduralConfig  # light; a Ctrl-C at start-up meets main()

    add_config_arguments(q, ProceduralConfig)
    q.set_defaults(handler="character_procedural")

    p = sub.add_parser("template", help="write template variants (original/smooth/coarse) with outer shells",
                       description="Write OUT/<variant>/ (a complete DynaCap character + outer.obj, the offset "
                                   "shell with the same vertex order and UVs) for original and, when asked, "
                                   "smooth and coarse, plus OUT/report.json.")
    from deliffas.data.template_config import TemplateConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, TemplateConfig)
    p.set_defaults(handler="template")


def _add_training_commands(sub) -> None:
    """zoo and train."""
    p = sub.add_parser("zoo", help="list the model zoo (named configurations and presets) and avatar files",
                       description="List every model of the zoo with its presets (atlas side S, MLP, feature "
                                   "channels, parameters) and, given FOLDER, the .avatar files under it.")
    from deliffas.engine.zoo_config import ZooConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, ZooConfig)
    p.set_defaults(handler="zoo")

    p = sub.add_parser("train", help="train a model of the zoo on converted shards",
                       description="Train on SHARDS (from `deliffas convert`). L1 first, then L1 + perceptual "
                                   "when --perceptual is given. Distributed with `torchrun --nproc_per_node N -m deliffas train ...`.")
    from deliffas.engine.auto_capacity_config import AutoCapacityConfig  # light; a Ctrl-C at start-up meets main()
    from deliffas.engine.train_config import TrainConfig

    add_config_arguments(p, TrainConfig, sparse=True)
    p.add_argument("--config", type=Path, default=None,
                   help="JSON file of TrainConfig fields (incl. model_overrides) (default: none)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint (on the same capture)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    p.add_argument("--auto-capacity", action="store_true",
                   help="search model capacities on the validation split and keep the cheapest within "
                        "--tolerance-db of the best foreground PSNR; the test split scores the chosen one only")
    add_config_arguments(p, AutoCapacityConfig)
    p.set_defaults(handler="train")


def _add_evaluation_commands(sub) -> None:
    """eval, render and export."""
    p = sub.add_parser("eval", help="evaluate a run: foreground and official PSNR/SSIM, FLIP (+LPIPS/FID when "
                                    "weights exist) and per-stage timing",
                       description="Score RUN on a split. Every number names its protocol: the official one (white "
                                   "composite, 600x496 crop: at small images mostly background) and the foreground "
                                   "block (padded mask box, masked PSNR), the headline.")
    from deliffas.engine.eval_config import EvalConfig  # light; imported here: a Ctrl-C at start-up meets main()
    from deliffas.engine.render_config import RenderConfig

    add_config_arguments(p, EvalConfig)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--fast", action="store_true",
                   help="render by the CPU fast path of 'deliffas render'/'view' (to measure what it changes)")
    p.set_defaults(handler="eval")

    p = sub.add_parser("render", help="free-viewpoint video of a trained avatar driven by a motion",
                       description="Render RUN (a run folder or an .avatar file) driven by a motion into a video or "
                                   "a folder of PNG frames, seen from a capture camera or an orbit. An orbit turns "
                                   "once over the video: the capture's test motion may have few frames, so pass "
                                   "--frames N --loop for a longer one.")
    add_config_arguments(p, RenderConfig)
    _add_plain_option(p)
    p.set_defaults(handler="render")

    p = sub.add_parser("export", help="write a run as one .avatar file (model, template, atlas, cameras)",
                       description="Write RUN's model (config and weights), template spec and source files, atlas, "
                                   "faces and capture cameras as one safetensors file with JSON metadata and "
                                   "sha256s (no pickle). 'deliffas render OUT.avatar --motion M' and 'deliffas view' "
                                   "load it anywhere, without the shards or the subject.")
    from deliffas.engine.export_config import ExportConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, ExportConfig)
    p.set_defaults(handler="export")


def _add_viewer_commands(sub) -> None:
    """view and demo."""
    p = sub.add_parser("view", help="interactive viewer in the browser (viser): a trained run, or a capture",
                       description="Serve a browser viewer of a trained run: free camera (orbit, pan, zoom), "
                                   "the capture's cameras as frustums and a menu, a motion timeline, RGB / uv / "
                                   "normal / U-Net feature views, the inner and outer meshes, ground truth and "
                                   "error at capture cameras, per-stage timing. Given a capture folder instead "
                                   "(no train_config.json), show the capture without a model: its cameras "
                                   "textured with the current frame's images (red = held-out), the posed "
                                   "template, and at a chosen camera its image with the template's silhouette "
                                   "(green), the mask edge (red) and their IoU, as 'deliffas check' scores them. "
                                   "Open the printed URL; over SSH forward the port "
                                   "(ssh -L 8080:127.0.0.1:8080 HOST). No authentication.")
    from deliffas.engine.view_config import SubjectViewConfig, ViewConfig  # light; a Ctrl-C at start-up meets main()

    add_config_arguments(p, ViewConfig)
    add_config_arguments(p, SubjectViewConfig, skip=("host", "port", "max_resolution"))  # the same options
    _add_plain_option(p)
    p.set_defaults(handler="view")

    p = sub.add_parser("demo", help="the whole path on the embedded procedural character, with a report",
                       description="Build the procedural character, render a synthetic capture, convert it, train, "
                                   "evaluate and render a video, and write OUT/report.md with every number.")
    from deliffas.engine.demo_config import DemoConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, DemoConfig)
    p.set_defaults(handler="demo")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deliffas", description="deliffas: deformable light-field human avatars (DELIFFAS) - templates, captures, shards, training, evaluation and rendering. `deliffas COMMAND --help` explains each command.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--version", action="version", version=f"deliffas {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("pose", help="write a template (DDC character or SMPL model) posed by one frame of a motion",
                       description="Pose TEMPLATE with frame N of MOTION and write the mesh in the template's "
                                   "vertex order, in mm. TEMPLATE is a .character (DDC: MOTION a .motion, DOF "
                                   "skeleton + skinning) or an SMPL model file .npz/.pkl (MOTION an AMASS-style "
                                   ".npz with poses, trans, betas; SMPL metres become mm).")
    from deliffas.data.pose_config import PoseConfig  # light; imported here: a Ctrl-C at start-up meets main()

    add_config_arguments(p, PoseConfig)
    p.set_defaults(handler="pose")
    for add in (_add_capture_commands, _add_capture_tool_commands, _add_geometry_commands, _add_training_commands,
                _add_evaluation_commands, _add_viewer_commands):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s")
        from deliffas.cli import handlers  # start-up time: parsing and --help must not import torch

        return int(getattr(handlers, f"cmd_{args.handler}")(args) or 0)
    except (ValueError, OSError) as err:  # bad input: every deliffas format/config error is a ValueError
        log.debug("traceback of the error below", exc_info=True)
        print(f"deliffas {args.command}: error: {_error_line(err)}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ImportError) as err:
        if not interrupted_import(err):  # an ImportError not caused by a Ctrl-C during the import
            raise
        from deliffas.cli.interrupted import report_interrupted

        return report_interrupted(args, argv)


_OS_HINTS = ((FileNotFoundError, "check the path"), (FileExistsError, "choose another path"),
             (PermissionError, "choose a path you may read or write"),
             (NotADirectoryError, "a file is where a folder is expected; check the path"))


def _error_line(err: Exception) -> str:
    """One line for a user: an OSError names its file, what failed and what to do (``[Errno 2] ...`` says none)."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror and str(err.filename) not in str(err.args[-1]):
        hint = next((h for kind, h in _OS_HINTS if isinstance(err, kind)), "")
        return f"{err.filename}: {err.strerror.lower()}" + (f"; {hint}" if hint else "")
    return str(err)
