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
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    from deliffas.data.text_lines import DynaCapFormatError

    try:
        return int(args.func(args) or 0)
    except (DynaCapFormatError, FileNotFoundError) as err:
        print(f"deliffas {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
