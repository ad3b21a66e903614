"""uv stage: ray-casting scenes + inner hit, outer hit and depth-peeled exit of one image.

Measured: the engine's uv stage from a camera to its shaded rays, ``UVRaycaster(inner, faces,
outer, atlas)`` (two scenes) + ``deliffas.engine.rays.camera_rays`` (pixel rays of the surfaces'
projected window, inner first hit, outer first hit, the depth-peeled outer exit where the inner
surface is missed (the only rays whose inner sample it is), uvs, the shaded-ray selection and
view directions), against the same-run baseline ``build_scene(inner)`` + one
open3d ``cast_rays`` of every pixel ray of the image on the inner mesh, those rays computed
beforehand and packed as an open3d float32 tensor (so the baseline pays no ray generation).
Target: stage <= 2.5 x baseline.

Also reported (no target): ``UVRaycaster.cast(camera)``, the dense full-image ``RaycastHits`` of
every pixel, for callers that need per-pixel arrays. Smoke mode: the smoke sizes of ``_avatar``.
"""

from __future__ import annotations

from benchmarks import _avatar
from benchmarks._timing import BENCH_THREADS, best_times
from benchmarks.common import Result

GROUP = "uv"
TARGET = 2.5


def run() -> list[Result]:
    return _avatar.avatar_run(GROUP, _run)


def _run(av: _avatar.Avatar) -> list[Result]:
    import numpy as np
    import open3d as o3d

    from deliffas.engine.rays import camera_rays
    from deliffas.geometry.raycast import UVRaycaster, build_scene, uv_inner_or_exit

    results = [Result(GROUP, "torch intra-op threads in the uv/mlp/unet/normals/lf_vs_nerf rows", BENCH_THREADS,
                      "threads", note="see benchmarks/_timing.py BENCH_THREADS")]
    for size, repeat in zip(_avatar.sizes(), (15, 7)):
        cam = _avatar.camera(av, size)
        origins, dirs = cam.rays()  # (N, 3) float64 each
        packed = np.concatenate([origins, dirs], axis=1).astype(np.float32)  # (N, 6)
        packed_o3d = o3d.core.Tensor(packed)

        def stage():
            return camera_rays(UVRaycaster(av.inner, av.faces, av.outer, av.atlas), cam)

        def dense():
            return UVRaycaster(av.inner, av.faces, av.outer, av.atlas).cast(cam)

        def baseline():
            return build_scene(av.inner, av.faces).cast_rays(packed_o3d)

        rays = stage()
        hits = dense()
        uv_in, _ = uv_inner_or_exit(hits)
        shaded = hits.outer_hit & np.isfinite(uv_in).all(-1) & np.isfinite(hits.uv_outer).all(-1)
        assert np.array_equal(rays.pixels, np.flatnonzero(shaded)), "camera_rays and the dense cast disagree"
        t = best_times({"stage": stage, "baseline": baseline, "dense": dense}, repeat=repeat, min_time=4.0)
        ratio = t["stage"] / t["baseline"]
        n = len(origins)
        results.append(Result(
            GROUP, f"{size}: 2 scenes + camera_rays (inner, outer, peeled exit), {n} px", t["stage"] * 1e3, "ms",
            baseline="build_scene(inner) + 1 open3d cast_rays of every pixel", ratio=ratio, target=f"<= {TARGET}",
            passed=ratio <= TARGET,
            note=(f"baseline {t['baseline'] * 1e3:.1f} ms; {av.source}; {rays.num_rays} shaded rays; hits: inner "
                  f"{int(hits.inner_hit.sum())}, outer {int(hits.outer_hit.sum())}, exit {int(hits.outer_exit_hit.sum())}"),
        ))  # fmt: skip
        results.append(Result(GROUP, f"{size}: baseline 1 scene + 1 cast_rays", t["baseline"] * 1e3, "ms"))
        results.append(Result(GROUP, f"{size}: 2 scenes + dense full-image cast(camera) (no target)", t["dense"] * 1e3,
                              "ms", ratio=t["dense"] / t["baseline"]))
    return results
