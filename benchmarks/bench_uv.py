"""uv stage: ray-casting scenes + inner hit, outer hit and depth-peeled exit of every pixel.

Measured: ``UVRaycaster(inner, faces, outer, atlas)`` (two scenes) and ``cast_rays`` of all
pixel rays of one camera (inner first hit, outer first hit, outer exit hit, uvs of all three),
against the same-run baseline ``build_scene(inner)`` + one open3d ``cast_rays`` of the same rays
(already packed as an open3d float32 tensor) on the inner mesh. The pixel rays
(``Camera.rays``) are computed once beforehand for both. Target: stage <= 2.5 x baseline.
"""

from __future__ import annotations

from benchmarks import _avatar
from benchmarks._timing import BENCH_THREADS, best_times, torch_threads
from benchmarks.common import Result

GROUP = "uv"
TARGET = 2.5


def run() -> list[Result]:
    with torch_threads():
        return _run()


def _run() -> list[Result]:
    import numpy as np
    import open3d as o3d

    from deliffas.geometry.raycast import UVRaycaster, build_scene

    try:
        av = _avatar.avatar()
    except _avatar.Unavailable as exc:
        return _avatar.skipped(GROUP, str(exc))
    results = [Result(GROUP, "torch intra-op threads in the uv/mlp/unet/normals/lf_vs_nerf rows", BENCH_THREADS,
                      "threads", note="see benchmarks/_timing.py BENCH_THREADS")]
    for size, repeat in (("256^2", 15), ("940x1285", 7)):
        cam = _avatar.camera(av, size)
        origins, dirs = cam.rays()  # (N, 3) float64 each
        packed = np.concatenate([origins, dirs], axis=1).astype(np.float32)  # (N, 6)
        packed_o3d = o3d.core.Tensor(packed)

        def stage():
            return UVRaycaster(av.inner, av.faces, av.outer, av.atlas).cast_rays(origins, dirs)

        def baseline():
            return build_scene(av.inner, av.faces).cast_rays(packed_o3d)

        hits = stage()
        t = best_times({"stage": stage, "baseline": baseline}, repeat=repeat, min_time=4.0)
        ratio = t["stage"] / t["baseline"]
        n = len(origins)
        results.append(Result(
            GROUP, f"{size}: 2 scenes + inner/outer/exit casts, {n} px", t["stage"] * 1e3, "ms",
            baseline="build_scene(inner) + 1 open3d cast_rays", ratio=ratio, target=f"<= {TARGET}",
            passed=ratio <= TARGET,
            note=(f"baseline {t['baseline'] * 1e3:.1f} ms; {av.source}; hits: inner {int(hits.inner_hit.sum())}, "
                  f"outer {int(hits.outer_hit.sum())}, exit {int(hits.outer_exit_hit.sum())}"),
        ))  # fmt: skip
        results.append(Result(GROUP, f"{size}: baseline 1 scene + 1 cast_rays", t["baseline"] * 1e3, "ms"))
    return results
