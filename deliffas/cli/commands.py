"""The commands of ``deliffas``: one table that :func:`deliffas.cli.build_parser` walks.

Each :class:`Command` row names its config dataclasses as ``"module:Class"`` strings (their fields become the
options, :func:`deliffas.cli.from_config.add_config_arguments`; resolved when the parser is built, so importing this
module imports no config), the handler ``cmd_<handler>`` of :mod:`deliffas.cli.handlers`, and the few functions
below that declare options which are no config field (``tests/cli/test_from_config.py`` lists them and why).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from deliffas.cli.from_config import DeprecatedAlias
from deliffas.options import image_size

__all__ = ["COMMANDS", "Command", "Config", "Extra"]

Extra = Callable[[argparse.ArgumentParser, tuple[type, ...]], None]
"""Adds options that are no config field: ``extra(parser, config classes of the row, in order)``."""


@dataclass(frozen=True)
class Config:
    """A config class with keywords for ``add_config_arguments`` (a plain ``"module:Class"`` string takes none)."""

    ref: str
    sparse: bool = False
    skip: tuple[str, ...] = ()


@dataclass(frozen=True)
class Command:
    """One (sub)command: its options are ``positionals``, then each config's fields with ``extra`` before
    ``configs[extra_at]`` (after them all when None); a command with ``subcommands`` has no handler of its own."""

    name: str
    help: str
    description: str
    configs: tuple[str | Config, ...] = ()
    handler: str | None = None
    extra: Extra | None = None
    extra_at: int | None = None
    positionals: Extra | None = None
    subcommands: tuple[Command, ...] = ()
    metavar: str = "COMMAND"
    """The subcommand's placeholder in usage lines (``dest`` is ``<name>_command``)."""


def _synth_out_dir(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """synth: ``synthesize_capture(out_dir, SynthConfig)``'s path."""
    p.add_argument("out_dir", type=Path, help="subject folder to write")


def _synth_size(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """synth: one option, two fields (``SynthConfig.width``, ``height``)."""
    synth = configs[0]
    p.add_argument("--size", type=image_size, default=None,
                   help=f"image size WxH (default {synth.width}x{synth.height})")


def _convert_paths(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """convert: ``convert(subject, out, ConvertConfig)``'s paths."""
    p.add_argument("subject", type=Path, help="subject folder (cameras.calibration, character/ or body/, "
                                              "training/, testing/)")
    p.add_argument("out", type=Path, help="output folder")


def _train_options(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """train: how the config is built (``--config``, ``--resume``) and which API runs (``--auto-capacity``)."""
    p.add_argument("--config", type=Path, default=None,
                   help="JSON file of TrainConfig fields (incl. model_overrides) (default: none)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint (on the same capture)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    p.add_argument("--auto-capacity", action="store_true",
                   help="search model capacities on the validation split and keep the cheapest within "
                        "--tolerance-db of the best foreground PSNR; the test split scores the chosen one only")


def _eval_options(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """eval: how the result is printed (``--json``); ``--fast``, the deprecated spelling of ``--render-path fast``."""
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--fast", action=DeprecatedAlias, dest="render_path.path", const="fast",
                   replacement="--render-path fast", help="deprecated: --render-path fast")


def _plain_option(p: argparse.ArgumentParser, configs: tuple[type, ...]) -> None:
    """render and view: ``--plain``, the deprecated spelling of ``--render-path plain``."""
    p.add_argument("--plain", action=DeprecatedAlias, dest="render_path.path", const="plain",
                   replacement="--render-path plain", help="deprecated: --render-path plain")


_DATA, _ENGINE = "deliffas.data", "deliffas.engine"

COMMANDS: tuple[Command, ...] = (
    Command("pose", "write a template (DDC character or SMPL model) posed by one frame of a motion",
            "Pose TEMPLATE with frame N of MOTION and write the mesh in the template's vertex order, in mm. "
            "TEMPLATE is a .character (DDC: MOTION a .motion, DOF skeleton + skinning) or an SMPL model file "
            ".npz/.pkl (MOTION an AMASS-style .npz with poses, trans, betas; SMPL metres become mm).",
            configs=(f"{_DATA}.pose_config:PoseConfig",), handler="pose"),
    Command("synth", "render a synthetic DynaCap capture with a loose garment",
            "Write a synthetic subject folder in DynaCap layout (cameras, the body: a DDC character or an SMPL "
            "model, training + novel-pose motions, RGBA images, optional videos, ground-truth .meshes). "
            "See docs/data.md.",
            configs=(f"{_DATA}.synth_config:SynthConfig",), handler="synth",
            positionals=_synth_out_dir, extra=_synth_size),
    Command("convert", "convert a capture into sharded HDF5",
            "Convert SUBJECT (image folders or videos) into HDF5 shards + meta.h5 + manifest.json under OUT "
            "(schema: docs/shards.md). SUBJECT is only read. The template (DDC character or SMPL model) is "
            "recorded in meta.h5.",
            configs=(f"{_DATA}.convert_config:ConvertConfig",), handler="convert", positionals=_convert_paths),
    Command("ingest", "turn a raw calibrated multi-view recording (videos + calibration) into a subject with masks "
                      "and a fitted body per frame",
            "Read RECORDING (one video or image folder per camera and a calibration in any format 'deliffas "
            "cameras' reads), detect the person in every frame (mask and 2-D keypoints, MediaPipe: pip install "
            "'deliffas[ingest]'), triangulate the keypoints, fit the body model (one shape, a pose per frame) to "
            "them and to the masks, and write a DynaCap subject to --out that check, convert and train read "
            "unchanged, with ingest_report.json and overlay pictures. See docs/own-recording.md.",
            configs=(f"{_DATA}.ingest.config:IngestConfig",), handler="ingest"),
    Command("fit-smpl", "fit SMPL to every frame of a capture (for converting it with SMPL)",
            "Fit an SMPL model (one shape, per-frame pose and translation) to the surface of every frame of "
            "SUBJECT (its posed template, or tracked .meshes), by symmetric closest-point distance. Writes "
            "OUT/<sequence>.npz (AMASS-style, with the capture's frame numbers) and OUT/fit.json (residuals in "
            "mm); then `deliffas convert SUBJECT SHARDS --template MODEL --motions training=OUT/training.npz "
            "--motions testing=OUT/testing.npz` converts it with SMPL.",
            configs=(f"{_DATA}.fit_smpl_config:FitSmplConfig",
                     "deliffas.geometry.smpl_surface_fit_config:SurfaceFitConfig"), handler="fit_smpl"),
    Command("check", "score the posed template's silhouette against the masks, per camera",
            "Parse SUBJECT, pose its template on a sample of frames, compare its silhouette with every camera's "
            "mask (IoU) and name likely causes of failures (pose direction, transposed R, OpenGL axes, m vs mm, "
            "frame offset, camera order). Writes OUT/report.md, overlays and summary.json; exit 1 when a camera "
            "fails.",
            configs=(f"{_DATA}.check_capture_config:CheckCaptureConfig", f"{_DATA}.check_config:CheckConfig",
                     f"{_DATA}.subject_options:SubjectOptions"), handler="check"),
    Command("verify", "check converted shards against their manifest",
            "Check every shard of OUT against manifest.json (presence, size, sha256, readability, completeness); "
            "exit 1 naming each broken shard.",
            configs=(f"{_DATA}.verify_config:VerifyConfig",), handler="verify"),
    Command("cameras", "convert cameras between capture formats (--help lists them)",
            "Read the cameras of SRC (a camera file or a capture folder; format detected unless --from) and write "
            "them to OUT in the format --to, converting units, directions, axes and the pixel-centre convention "
            "(docs/data.md section 6). Lens distortion the target cannot hold is an error unless "
            "--drop-distortion. Shorthands kept from earlier releases: CALIBRATION --to-colmap DIR and "
            "CALIBRATION --from-colmap DIR (writes CALIBRATION).",
            configs=("deliffas.io.camera_config:CamerasConfig",), handler="cameras"),
    Command("character", "build characters (subcommand: procedural)", "Build DynaCap characters.", metavar="KIND",
            subcommands=(
                Command("procedural", "write the license-free procedural character",
                        "Build the procedural human (watertight template, Skeletool skeleton with DDC DOF names, "
                        "skin, UVs, texture, segmentation with a skirt, embedded graph) and write it as a DynaCap "
                        "character into OUT_DIR.",
                        configs=("deliffas.geometry.procedural_config:ProceduralConfig",),
                        handler="character_procedural"),
            )),
    Command("template", "write template variants (original/smooth/coarse) with outer shells",
            "Write OUT/<variant>/ (a complete DynaCap character + outer.obj, the offset shell with the same vertex "
            "order and UVs) for original and, when asked, smooth and coarse, plus OUT/report.json.",
            configs=(f"{_DATA}.template_config:TemplateConfig",), handler="template"),
    Command("zoo", "list the model zoo (named configurations and presets) and avatar files",
            "List every model of the zoo with its presets (atlas side S, MLP, feature channels, parameters) and, "
            "given FOLDER, the .avatar files under it.",
            configs=(f"{_ENGINE}.zoo_config:ZooConfig",), handler="zoo"),
    Command("train", "train a model of the zoo on converted shards",
            "Train on SHARDS (from `deliffas convert`). L1 first, then L1 + perceptual when --perceptual is given. "
            "Distributed with `torchrun --nproc_per_node N -m deliffas train ...`.",
            configs=(Config(f"{_ENGINE}.train_config:TrainConfig", sparse=True),
                     f"{_ENGINE}.auto_capacity_config:AutoCapacityConfig"),
            handler="train", extra=_train_options, extra_at=1),
    Command("eval", "evaluate a run: foreground and official PSNR/SSIM, FLIP (+LPIPS/FID when weights exist) and "
                    "per-stage timing",
            "Score RUN on a split. Every number names its protocol: the official one (white composite, 600x496 "
            "crop: at small images mostly background) and the foreground block (padded mask box, masked PSNR), "
            "the headline.",
            configs=(f"{_ENGINE}.eval_config:EvalConfig",), handler="eval", extra=_eval_options),
    Command("render", "free-viewpoint video of a trained avatar driven by a motion",
            "Render RUN (a run folder or an .avatar file) driven by a motion into a video or a folder of PNG "
            "frames, seen from a capture camera or an orbit. An orbit turns once over the video: the capture's "
            "test motion may have few frames, so pass --frames N --loop for a longer one.",
            configs=(f"{_ENGINE}.render_config:RenderConfig",), handler="render", extra=_plain_option),
    Command("export", "write a run as one .avatar file (model, template, atlas, cameras), or as a web page (--web)",
            "Write RUN's model (config and weights), template spec and source files, atlas, faces and capture "
            "cameras as one safetensors file with JSON metadata and sha256s (no pickle). 'deliffas render "
            "OUT.avatar --motion M' and 'deliffas view' load it anywhere, without the shards or the subject. "
            "With --web, OUT is a folder: a static page that plays the avatar in a browser (WebGL2), with no "
            "server-side code (docs/web.md).",
            configs=(f"{_ENGINE}.export_config:ExportConfig",), handler="export"),
    Command("view", "interactive viewer in the browser (viser): a trained run, or a capture",
            "Serve a browser viewer of a trained run: free camera (orbit, pan, zoom), the capture's cameras as "
            "frustums and a menu, a motion timeline, RGB / uv / normal / U-Net feature views, the inner and outer "
            "meshes, ground truth and error at capture cameras, per-stage timing. Given a capture folder instead "
            "(no train_config.json), show the capture without a model: its cameras textured with the current "
            "frame's images (red = held-out), the posed template, and at a chosen camera its image with the "
            "template's silhouette (green), the mask edge (red) and their IoU, as 'deliffas check' scores them. "
            "Open the printed URL; over SSH forward the port (ssh -L 8080:127.0.0.1:8080 HOST). "
            "No authentication.",
            configs=(f"{_ENGINE}.view_config:ViewConfig",  # the subject viewer shares the server's options:
                     Config(f"{_ENGINE}.view_config:SubjectViewConfig", skip=("host", "port", "max_resolution"))),
            handler="view", extra=_plain_option),
    Command("demo", "the whole path on the embedded procedural character, with a report",
            "Build the procedural character, render a synthetic capture, convert it, train, evaluate and render "
            "a video, and write OUT/report.md with every number.",
            configs=(f"{_ENGINE}.demo_config:DemoConfig",), handler="demo"),
)
"""Every command, in the order ``deliffas --help`` lists them."""
