"""The uv maps of both surfaces (inner and outer, with depth peeling) seen by a camera read from another format.

    python examples/02_uv_maps.py OUT --cameras CAMERAS [--format colmap|easymocap|...] [--size WxH]

CAMERAS is any camera file or folder ``deliffas.io.camera_formats.read_cameras`` reads (a COLMAP
model, an EasyMocap folder with intri.yml/extri.yml, a DynaCap .calibration, ...). The template is
the procedural character in its rest pose, placed 3 m in front of the first camera when the cameras
are not around it. Writes OUT/uv_<camera>.png (u, v of the outer surface in R, G; inner in B).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from deliffas.geometry.atlas import UVAtlas
from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character
from deliffas.geometry.raycast import UVRaycaster, uv_inner_or_exit
from deliffas.geometry.shell import offset_shell
from deliffas.geometry.templates import build_template, ddc_spec
from deliffas.io.camera_formats import read_cameras


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--cameras", type=Path, required=True, help="camera file or folder (any supported format)")
    parser.add_argument("--format", default="auto", help="camera format (default: detected)")
    parser.add_argument("--size", default=None, help="WxH for formats that store no image size")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    cameras = read_cameras(args.cameras, args.format, size)  # deliffas convention: mm, world -> camera

    path = make_procedural_character(ProceduralConfig(args.out / "character", target_faces=3000, texture_size=256))
    template = build_template(ddc_spec(path), dtype=torch.float64)
    inner = template.rest_verts.numpy()
    target = cameras[0].center + 3000.0 * cameras[0].R[2]  # 3 m along the first camera's optical axis
    inner = inner - inner.mean(0) + target
    faces = template.faces.numpy()
    outer = offset_shell(inner, faces, 30.0)
    raycaster = UVRaycaster(inner, faces, outer, UVAtlas(template.uvs.numpy(), template.face_uvs.numpy()))

    for cam in cameras:
        hits = raycaster.cast(cam)  # (H, W) first outer hit, inner hit, outer exit (depth peeling)
        uv_in, _ = uv_inner_or_exit(hits)
        image = np.zeros((cam.height, cam.width, 3), np.float32)
        image[..., :2] = np.nan_to_num(hits.uv_outer)
        image[..., 2] = np.nan_to_num(uv_in[..., 0])
        cv2.imwrite(str(args.out / f"uv_{cam.name}.png"), (image[..., ::-1] * 255).astype(np.uint8))
        print(f"{cam.name}: {int(hits.outer_hit.sum())} pixels see the avatar")


if __name__ == "__main__":
    main()
