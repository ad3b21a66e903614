"""Pose a template, build its offset shell, uv atlas and temporal normal maps, and save them.

    python examples/01_geometry.py OUT [--character C.character --motion M.motion] [--frames 8] [--atlas 256]

Without a character, the license-free procedural character is built into OUT/character. Writes
OUT/posed_<f>.obj (inner surface, template order, mm), OUT/shell_<f>.obj (the 30 mm outer surface)
and OUT/normal_maps.npz (inner/outer temporal normal maps, (N, 3 (T + 1), S, S) float16).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from deliffas.geometry.atlas import UVAtlas, uv_texel_table
from deliffas.geometry.frame_geometry import FrameGeometryBuilder
from deliffas.geometry.motion_gen import procedural_motion
from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character
from deliffas.geometry.templates import build_template, ddc_spec
from deliffas.io.formats.dynacap.character import read_character, read_motion
from deliffas.io.mesh_files import write_mesh


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--character", type=Path, help=".character (default: the procedural character)")
    parser.add_argument("--motion", type=Path, help=".motion of the character (default: a procedural motion)")
    parser.add_argument("--frames", type=int, default=8, help="frames to pose (default 8)")
    parser.add_argument("--atlas", type=int, default=256, help="normal-map side S (default 256)")
    parser.add_argument("--window", type=int, default=2, help="temporal window T (default 2)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    path = args.character or make_procedural_character(ProceduralConfig(args.out / "character", target_faces=3000,
                                                                                texture_size=256))
    character = read_character(path)
    template = build_template(ddc_spec(path), dtype=torch.float64)  # the one way to build any template kind
    if args.motion:
        dofs = read_motion(args.motion, template.num_dofs).dofs[: args.frames]
    else:
        dofs = procedural_motion(character.skeleton, args.frames, seed=0, rest_dofs=character.rest_dofs).dofs
    with torch.no_grad():
        inner = template.pose(torch.as_tensor(dofs, dtype=torch.float64)).numpy()  # (N, V, 3) mm

    faces = template.faces.numpy()
    uvs, face_uvs = template.uvs.numpy(), template.face_uvs.numpy()
    table = uv_texel_table(UVAtlas(uvs, face_uvs), args.atlas)  # which face and barycentrics each texel samples
    geometry = FrameGeometryBuilder(faces, np.full(len(inner[0]), 30.0), table).build(inner)  # 30 mm shell

    for f in range(len(inner)):
        write_mesh(args.out / f"posed_{f:03d}.obj", geometry.inner[f], faces, uvs, face_uvs)
        write_mesh(args.out / f"shell_{f:03d}.obj", geometry.outer[f], faces, uvs, face_uvs)
    windows = [geometry.window(f, args.window) for f in range(len(inner))]  # frames f, f-1, ..., f-T
    np.savez_compressed(args.out / "normal_maps.npz",
                        inner=torch.stack([w[0] for w in windows]).numpy().astype(np.float16),
                        outer=torch.stack([w[1] for w in windows]).numpy().astype(np.float16))
    print(f"wrote {len(inner)} posed meshes, shells and {args.atlas}x{args.atlas} temporal normal maps to {args.out}")


if __name__ == "__main__":
    main()
