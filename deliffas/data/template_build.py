"""Template variants with their outer shells and a validity report, on disk: the API behind ``deliffas template``.

For a character this writes ``out_dir/<variant>/`` for ``original`` and, when asked, ``smooth``
(Taubin, same topology) and ``coarse`` (decimated, attributes transferred; see
``deliffas.geometry.variants``). Each folder holds a complete DynaCap character
``<variant>.character`` (+ .skeleton/.obj/.skin/.motion/texture/segmentation/graph) and
``outer.obj``: the offset shell of the rest-pose template (``deliffas.geometry.shell``), same vertex
order, faces and per-corner UVs. ``out_dir/report.json`` gathers counts, watertightness, the shell
reports and atlas statistics per variant.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from deliffas.io.infra.files import claim_output
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.io.formats.dynacap.character import Character, ObjData, read_character, write_obj
from deliffas.geometry.atlas import UVAtlas, uv_texel_table
from deliffas.geometry.shell import ShellConfig, offset_shell, shell_offsets, shell_report
from deliffas.geometry.variants import coarse_variant, smooth_variant, write_variant
from deliffas.data.template_config import TemplateConfig

__all__ = ["VARIANTS", "TemplateConfig", "build_templates", "atlas_info"]

log = logging.getLogger(__name__)

VARIANTS = ("original", "smooth", "coarse")


def atlas_info(mesh: ObjData, atlas_res: int) -> dict:
    """Statistics of a mesh's per-corner UV atlas at an S x S texel grid (JSON-ready)."""
    atlas = UVAtlas(mesh.uvs, mesh.face_uvs)
    table = uv_texel_table(atlas, atlas_res, gutter=0)
    corner = atlas.corner_uvs
    area = 0.5 * np.abs((corner[:, 1, 0] - corner[:, 0, 0]) * (corner[:, 2, 1] - corner[:, 0, 1])
                        - (corner[:, 2, 0] - corner[:, 0, 0]) * (corner[:, 1, 1] - corner[:, 0, 1]))
    return {
        "num_uvs": int(len(mesh.uvs)),
        "num_seam_vertices": int(len(np.unique(mesh.face_uvs)) - mesh.num_verts),
        "resolution": int(atlas_res),
        "texel_coverage": float(table.covered.mean()),
        "uv_area": float(area.sum()),
        "num_degenerate_uv_faces": int(len(table.degenerate_faces)),
        "uvs_in_unit_square": bool(((mesh.uvs >= 0) & (mesh.uvs <= 1)).all()),
    }


def _ensure_uvs(character: Character, atlas_res: int) -> tuple[Character, str]:
    """The character with UVs: its own, or a new xatlas atlas when the OBJ has none."""
    if character.mesh.has_uvs:
        return character, "file"

    log.warning("%s: the template has no per-corner UVs; generating an xatlas atlas", character.path)
    atlas = UVAtlas.from_mesh(character.mesh.verts, character.mesh.faces, resolution=atlas_res, padding=4)
    mesh = dataclasses.replace(character.mesh, uvs=np.array(atlas.uvs), face_uvs=np.array(atlas.face_uvs))
    return dataclasses.replace(character, mesh=mesh, texture=None), "xatlas"


def build_templates(config: TemplateConfig) -> dict:
    """Write the template variants of ``config.character`` with their outer shells and a report into ``config.out``
    (each field: :class:`TemplateConfig`).

    Returns:
        The report (also written as ``report.json``): ``{"character", "offset_mm", "safe", "variants":
        {name: {"character", "outer", "num_verts", "num_faces", "watertight", "num_graph_nodes",
        "uv_source", "atlas", "shell", "seconds"}}}``.
    """
    smooth_iters, coarse_faces, offset_mm, atlas_res = (config.smooth_iters, config.coarse_faces, config.offset_mm,
                                                        config.atlas_res)
    if smooth_iters is not None and smooth_iters < 0:
        raise ValueError(f"smooth_iters: expected >= 0, got {smooth_iters}")
    if coarse_faces is not None and coarse_faces < 4:
        raise ValueError(f"coarse_faces: expected >= 4, got {coarse_faces}")
    if offset_mm <= 0:
        raise ValueError(f"offset_mm: expected > 0, got {offset_mm}")
    out = claim_output(config.out, config.overwrite, "report.json", "template variants")
    original, uv_source = _ensure_uvs(read_character(config.character), atlas_res)
    jobs = [("original", lambda: original)]
    if smooth_iters is not None:
        jobs.append(("smooth", lambda: smooth_variant(original, smooth_iters)))
    if coarse_faces is not None:
        jobs.append(("coarse", lambda: coarse_variant(original, coarse_faces, atlas_res=atlas_res)))
    shell_config = ShellConfig(offset_mm=float(offset_mm), safe=bool(config.safe))
    report = {"character": str(Path(config.character)), "offset_mm": float(offset_mm), "safe": bool(config.safe),
              "variants": {}}
    for name, make in jobs:  # at most three variants
        t0 = time.perf_counter()
        character = make()
        folder = out / name
        path = write_variant(folder, character, name)
        mesh = character.mesh
        offsets = shell_offsets(mesh.verts, mesh.faces, shell_config)
        outer = offset_shell(mesh.verts, mesh.faces, offsets)
        write_obj(folder / "outer.obj", ObjData(np.asarray(outer), mesh.faces, mesh.uvs, mesh.face_uvs))
        shell = shell_report(mesh.verts, mesh.faces, outer, offsets=offsets, offset_mm=offset_mm)
        report["variants"][name] = {
            "character": str(path),
            "outer": str(folder / "outer.obj"),
            "num_verts": mesh.num_verts,
            "num_faces": mesh.num_faces,
            "watertight": bool(shell.watertight),
            "num_graph_nodes": None if character.graph is None else character.graph.num_verts,
            "uv_source": uv_source if name != "coarse" else "xatlas",
            "atlas": atlas_info(mesh, atlas_res),
            "shell": shell.to_dict(),
            "seconds": round(time.perf_counter() - t0, 3),
        }
        log.info("template %s: %d verts, %d faces, watertight %s, shell self-intersections %d", name,
                 mesh.num_verts, mesh.num_faces, shell.watertight, shell.num_self_intersecting_faces)
    write_text_atomic(out / "report.json", json.dumps(report, indent=2) + "\n")  # last: marks a finished build
    return report
