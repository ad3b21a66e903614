"""What ``synthesize_capture`` renders (:class:`SynthConfig`, :class:`ShadingConfig`); light, so the CLI reads
it without torch."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from deliffas.options import count_or_indices, opt, positive_int

__all__ = ["SynthConfig", "ShadingConfig", "IMAGES_KEY", "STRAIGHT_IMAGES", "check_synth_images"]

IMAGES_KEY = "images"
"""Key of ``synth.json`` that says what the RGB of the written images means."""
STRAIGHT_IMAGES = "straight"
"""Its value: straight colour (not premultiplied by the coverage alpha), as a photograph and its mask."""



@dataclass(frozen=True)
class ShadingConfig:
    """Fixed light and material of the synthetic captures."""
    light_dir: tuple[float, float, float] = (0.35, 0.85, 0.55)
    """Direction from the subject towards the (directional) light, world frame (normalised here)."""
    ambient: float = 0.35
    """Ambient term, multiplied by the ambient occlusion."""
    diffuse: float = 0.7
    """Lambert term."""
    specular: float = 0.3
    """Blinn-Phong specular strength (white light)."""
    shininess: float = 24.0
    """Blinn-Phong exponent."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """RGB in [0, 1] behind the subject."""
    supersample: int = 1
    """s: s x s rays per pixel (anti-aliased coverage alpha); 1 = one ray through the pixel centre."""



@dataclass(frozen=True)
class SynthConfig:
    """What ``synthesize_capture`` renders."""
    num_frames: int = opt(20, help="training frames", flag="--frames", parse=positive_int)
    num_test_frames: int | None = opt(None, help="novel-pose frames", flag="--test-frames", parse=positive_int,
                                      default_text="frames // 2")
    num_cameras: int = opt(8, help="cameras of the dome, at least 2", flag="--cameras", parse=positive_int)
    width: int = 256
    """Image width in pixels."""
    height: int = 256
    """Image height in pixels."""
    test_cameras: int | tuple[int, ...] | None = opt(None, help="held-out cameras: a count N or a list a,b,...",
                                                     parse=count_or_indices, default_text="max(1, cameras // 8)")
    seed: int = opt(0, help="random seed of the character, the motions, the camera dome and the AO sampling")
    character: str | None = opt(None, help=".character to use instead of the procedural character (copied into the "
                                           "subject)",
                                default_text="the procedural character, built into OUT_DIR/character")
    body_model: str | None = opt(None, help="render an SMPL body instead of a DDC character: an SMPL model file "
                                            "(.npz/.pkl, official layout; not shipped, license) or 'procedural' (the "
                                            "license-free body in SMPL layout)", metavar="MODEL|procedural",
                                 default_text="a DDC character")
    body_uv: str | None = opt(None, help="OBJ with the SMPL model's uv layout", default_text="an xatlas atlas")
    motion: str | None = opt(None, help="training motion (its first --frames frames): .motion (DDC) or AMASS-style "
                                        ".npz (SMPL)",
                             default_text="a procedural motion")
    test_motion: str | None = opt(None, help="novel-pose motion, as --motion (default: a procedural one with another "
                                             "seed)", default_text="procedural, another seed")
    videos: bool = opt(False, help="also write FFV1 videos img/c_<cam>.avi + fg/c_<cam>.avi")
    jobs: int = opt(1, help="rendering processes (the frames are split between them)", parse=positive_int)
    fps: float = 25.0
    """Frame rate: velocities of the garment model and of the videos."""
    supersample: int = opt(1, help="s x s rays per pixel (anti-aliased coverage alpha)", parse=positive_int)
    garment_min_mm: float = 20.0
    """Smallest outward displacement inside the garment region."""
    garment_max_mm: float = 60.0
    """Largest outward displacement."""
    skinning: Literal["dqs", "lbs"] = "dqs"
    """Skinning of the template the garment is added to."""
    camera_distance_mm: tuple[float, float] = (3000.0, 4000.0)
    """Range of camera distances from the subject centre."""
    camera_elevation_deg: tuple[float, float] = (-5.0, 35.0)
    """Range of camera elevations."""
    ao_rays: int = 16
    """Hemisphere rays per vertex of the ambient-occlusion proxy."""
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    """Light and material."""
    overwrite: bool = opt(False, help="replace an earlier synthetic capture in OUT_DIR (a non-empty folder is "
                                      "refused otherwise)")


def check_synth_images(root: str | Path) -> None:
    """Refuse a synthetic capture whose supersampled images are premultiplied by their coverage.

    ``synth`` wrote colour x coverage (premultiplied) before ``synth.json`` carried
    ``"images": "straight"``; with ``--supersample 1`` both are the same bytes (binary alpha), so only
    a supersampled capture without the key is refused. A folder without ``synth.json`` (a real capture)
    passes.

    Raises:
        ValueError: naming ``synth.json``, the key and the command that re-renders the capture.
    """
    path = Path(root) / "synth.json"
    if not path.is_file():
        return
    record = json.loads(path.read_text())
    supersample = int(record.get("config", {}).get("supersample", 1))
    if supersample > 1 and record.get(IMAGES_KEY) != STRAIGHT_IMAGES:
        raise ValueError(f"{path}: key {IMAGES_KEY!r} is {record.get(IMAGES_KEY)!r}, expected {STRAIGHT_IMAGES!r} "
                         f"(rendered with --supersample {supersample} by an older synth: its edge pixels are "
                         f"premultiplied by their coverage); re-render it: deliffas synth {Path(root)} --supersample "
                         f"{supersample} --overwrite, with the other options under 'config' in synth.json")
