"""The scene of a web export: the mesh and its atlas, the normal-map gather, the outer offsets, the capture
cameras and the motion.

The motion is what the player poses per frame: for a template posed by skinning alone (a DDC character) the
per-frame bone transforms with the skin's indices and weights (the player blends them by LBS or DQS, as the
template does); for any other template the posed vertices of every frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from deliffas.data.pose_motions import read_pose_motion
from deliffas.data.shard_meta import ShardMeta
from deliffas.engine.render import DEFAULT_FRAMES, motion_geometry_builder
from deliffas.engine.web.bundle import Bundle
from deliffas.geometry.templates.ddc import DDCTemplate
from deliffas.io.motion import Motion

__all__ = ["pack_scene"]


def _pack_motion(template, dofs: np.ndarray, bundle: Bundle) -> dict:
    """Bone transforms and skin (a skinned template) or posed vertices per frame."""
    params = torch.as_tensor(dofs, dtype=torch.float64)
    if type(template) is DDCTemplate:  # posed by skinning alone (a subclass poses by more)
        bones = template.bone_transforms(params)[:, :, :3, :].numpy()  # (N, Bn, 3, 4)
        return {"kind": "skinned", "skinning": template.skinning, "frames": len(dofs),
                "rest_verts": bundle.add("rest_verts", template.rest_verts.numpy()),
                "bones": bundle.add("bones", bones),
                "skin_indices": bundle.add("skin_indices", template.skin_indices.numpy(), "int32"),
                "skin_weights": bundle.add("skin_weights", template.skin_weights.numpy())}
    verts = template.pose(params).numpy()
    return {"kind": "vertices", "frames": len(dofs), "verts": bundle.add("verts", verts)}


def pack_scene(meta: ShardMeta, motion_path: Path, frames: int | None, bundle: Bundle) -> dict:
    """The scene's JSON entry, its arrays added to ``bundle``."""
    template, builder = motion_geometry_builder(meta)
    motion: Motion = read_pose_motion(motion_path, meta.template_spec(), template.num_dofs)
    n = min(frames or DEFAULT_FRAMES, motion.num_frames)
    gather = builder.gather
    cameras = [{"name": c.name, "K": np.asarray(c.K).tolist(), "world_to_cam": np.asarray(c.world_to_cam).tolist(),
                "width": int(c.width), "height": int(c.height)} for c in meta.cameras()]
    test = [int(c) for c in np.asarray(meta.test_cameras).reshape(-1)]
    with torch.no_grad():
        posing = _pack_motion(template, motion.dofs[:n], bundle)
    return {"motion_file": Path(motion_path).name, "num_verts": int(len(builder.offsets)),
            "faces": bundle.add("faces", builder.faces, "int32"),
            "uvs": bundle.add("uvs", meta.uvs), "face_uvs": bundle.add("face_uvs", meta.face_uvs, "int32"),
            "offsets": bundle.add("offsets", builder.offsets),
            "texel_verts": bundle.add("texel_verts", gather.vert_index.numpy(), "int32"),
            "texel_weights": bundle.add("texel_weights", gather.weights.numpy()),
            "cameras": cameras, "test_cameras": test, "motion": posing}
