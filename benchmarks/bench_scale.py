"""The paper's data scale: conversion of a 1285 x 940, 8-camera, 30-frame capture at atlas S = 1024.

Rows: conversion images per CPU-second (one process, setup excluded; CPU time, so the figure is
per core whatever else runs on the shared machine, with the wall-clock rate beside it), its split
into set-up, a per-frame and a per-image cost (three runs: 8 cameras x 30 frames, 2 x 30, 8 x 10),
the peak resident set of a converting worker (one process; and each of a 2-worker LocalCluster),
shard bytes per frame and per image, and ``ShardDataset`` samples/s (K = 4 cameras) on the
shards. docs/scale.md extrapolates a full DynaCap subject from them. The capture is synthesized once into
``bench_out/paper_capture`` (deterministic, seed 0) and reused by later runs. Smoke mode: the same runs on a
64 x 48, 5-camera, 6-frame capture at S = 32 in a temporary folder, with the bench capture's character.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from benchmarks.common import Result, smoke

WIDTH, HEIGHT, CAMERAS, FRAMES, ATLAS = 1285, 940, 8, 30, 1024
"""The paper's image size (as bench_engine renders it), a DynaCap-like rig subset, its atlas side S."""
SHARD_FRAMES = 10
K = 4
WORKER_RSS_TARGET = 3 << 30
"""Peak resident set a converting worker must stay under at this size, bytes (independent of frames and cameras)."""
CAPTURE_DIR = Path(os.environ.get("DELIFFAS_PAPER_CAPTURE", "bench_out/paper_capture"))


class ScaleSize(NamedTuple):
    """The scale capture: image width and height, cameras, frames, atlas side S, frames per shard."""

    width: int
    height: int
    cameras: int
    frames: int
    atlas: int
    shard_frames: int


FULL = ScaleSize(WIDTH, HEIGHT, CAMERAS, FRAMES, ATLAS, SHARD_FRAMES)
SMOKE = ScaleSize(64, 48, 5, 6, 32, 2)


def _setting() -> tuple[ScaleSize, Path]:
    """The capture's size and folder: :data:`FULL` in :data:`CAPTURE_DIR`, or :data:`SMOKE` in a new temporary
    folder in smoke mode."""
    if smoke():
        return SMOKE, Path(tempfile.mkdtemp(prefix="deliffas-bench-scale-"))
    return FULL, CAPTURE_DIR


def paper_capture(dims: ScaleSize = FULL, folder: Path = CAPTURE_DIR) -> Path:
    """The synthetic subject of size ``dims`` in ``folder`` (made once; ``capture.json`` records how). In smoke
    mode with the bench capture's character (no procedural character built a second time)."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    record = {"width": dims.width, "height": dims.height, "cameras": dims.cameras, "frames": dims.frames, "seed": 0}
    done = folder / "capture.json"
    if done.is_file() and json.loads(done.read_text()) == record:
        return folder / "subject"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    character = None
    if smoke():
        from benchmarks._capture import bench_capture

        character = str(next((bench_capture()[0] / "character").glob("*.character")))
    t0 = time.perf_counter()
    synthesize_capture(folder / "subject", SynthConfig(num_frames=dims.frames, num_test_frames=1,
                                                       num_cameras=dims.cameras, width=dims.width, height=dims.height,
                                                       seed=0, character=character))
    done.write_text(json.dumps({**record, "synth_seconds": time.perf_counter() - t0}))
    return folder / "subject"


def _probe(subject: Path, out: Path, dims: ScaleSize, **config) -> dict:
    """One conversion in a fresh process (benchmarks._convert_probe): timings and worker peak RSS."""
    shutil.rmtree(out, ignore_errors=True)
    cfg = {"atlas_res": dims.atlas, "shard_frames": dims.shard_frames, "sequences": ["training"], **config}
    proc = subprocess.run([sys.executable, "-m", "benchmarks._convert_probe", str(subject), str(out), json.dumps(cfg)],
                          capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _dataset_rate(shards: Path) -> tuple[float, float]:
    """(samples/s wall, samples per CPU-second) of ``ShardDataset`` items (K cameras) at random frames."""
    from deliffas.data.dataset import ShardDataset

    ds = ShardDataset(shards, split="train", cameras_per_item=K, protocol="all")
    rng = np.random.default_rng(0)
    indices = [(int(rng.integers(len(ds.frames))), tuple(int(c) for c in rng.choice(ds.cameras, K, replace=False)))
               for _ in range(2 * len(ds.frames))]
    ds[indices[0]]  # open the shards
    t0, c0 = time.perf_counter(), time.process_time()
    for i in indices:
        ds[i]
    return len(indices) / (time.perf_counter() - t0), len(indices) / (time.process_time() - c0)


def cost_model(full: dict, two_cameras: dict, third: dict) -> dict:
    """CPU seconds of a conversion = setup + frames x per_frame + images x per_image, solved from three runs
    (8 cameras x 30 frames, 2 cameras x 30 frames, 8 cameras x 10 frames)."""
    per_image = (full["cpu_seconds"] - two_cameras["cpu_seconds"]) / (
        full["images_converted"] - two_cameras["images_converted"])
    per_frame = (full["cpu_seconds"] - third["cpu_seconds"] - per_image * (
        full["images_converted"] - third["images_converted"])) / (full["frames_converted"] - third["frames_converted"])
    setup = full["cpu_seconds"] - per_frame * full["frames_converted"] - per_image * full["images_converted"]
    return {"per_image": per_image, "per_frame": per_frame, "setup": setup}


def run() -> list[Result]:
    dims, folder = _setting()
    subject = paper_capture(dims, folder)
    work = folder / "out"
    full = _probe(subject, work / "all", dims)
    two = _probe(subject, work / "two", dims, cameras=[0, 1])
    third = _probe(subject, work / "third", dims, frames=f"0:{dims.frames // 3}")
    dask = _probe(subject, work / "dask", dims, dask_workers=2)
    load = os.getloadavg()[0]
    mib = 1 << 20
    model = cost_model(full, two, third)
    images = full["images_converted"]
    work_cpu = full["cpu_seconds"] - model["setup"]
    shards = sorted((work / "all" / "shards").glob("*.h5"))
    shard_bytes = [p.stat().st_size for p in shards]
    geometry_bytes = _geometry_bytes(work / "all")
    peak = full["worker_peak_rss"][0]
    note = f"load {load:.1f} on {os.cpu_count()} cores"
    wall, per_cpu = _dataset_rate(work / "all")
    rows = [
        Result("scale", f"convert {dims.width}x{dims.height}, {dims.cameras} cams, S={dims.atlas}, per CPU-s",
               images / work_cpu, "images/s",
               note=f"per core (jobs 1, CPU time, setup excl.); {dims.cameras} cams x {dims.frames} frames"),
        Result("scale", "  the same, wall clock on this shared machine",
               images / (full["seconds"] - full["seconds_setup"]), "images/s", note=note),
        Result("scale", "  cost per frame (posing, surfaces, normal maps, stored)", model["per_frame"], "CPU s",
               note=f"from runs of {dims.cameras} cams x {dims.frames} frames, 2 cams x {dims.frames}, "
                    f"{dims.cameras} cams x {dims.frames // 3}"),
        Result("scale", "  cost per image (read, encode, write)", model["per_image"], "CPU s"),
        Result("scale", "  set-up per worker (template, texel table, meta.h5)", model["setup"], "CPU s"),
        Result("scale", "peak RSS of a converting worker (jobs 1 process)", peak / mib, "MiB",
               target=f"<= {WORKER_RSS_TARGET / mib:.0f}", passed=peak <= WORKER_RSS_TARGET),
        Result("scale", "peak RSS per Dask worker (LocalCluster of 2)", max(dask["worker_peak_rss"]) / mib, "MiB",
               target=f"<= {WORKER_RSS_TARGET / mib:.0f}", passed=max(dask["worker_peak_rss"]) <= WORKER_RSS_TARGET,
               note="workers: " + ", ".join(f"{p / mib:.0f}" for p in dask["worker_peak_rss"])),
        Result("scale", "convert on a Dask LocalCluster of 2 workers, wall clock",
               dask["images_converted"] / (dask["seconds"] - dask["seconds_setup"]), "images/s",
               note=f"{note}; incl. worker start-up"),
        Result("scale", f"shard of {dims.shard_frames} frames x {dims.cameras} cams", float(np.mean(shard_bytes)) / mib,
               "MiB",
               note=f"{len(shards)} shards; {(sum(shard_bytes) - geometry_bytes) / images / mib:.3f} MiB per image "
                    f"(raw codec, synthetic), {geometry_bytes / full['frames_converted'] / mib:.1f} MiB geometry per "
                    f"frame"),
        Result("scale", f"ShardDataset S={dims.atlas}, K={K} cams/item, 0 workers, per CPU-s", per_cpu, "samples/s"),
        Result("scale", "  the same, wall clock on this shared machine", wall, "samples/s", note=note),
    ]
    (folder / "scale.json").write_text(json.dumps({"full": full, "two_cameras": two, "ten_frames": third,
                                                   "dask2": dask, "model": model, "load": load,
                                                   "geometry_bytes": geometry_bytes,
                                                   "rows": [r.to_dict() for r in rows]}, indent=1))
    return rows


def _geometry_bytes(shards: Path) -> int:
    """Stored bytes of everything in the shards but the images (normal maps, vertices, poses)."""
    import h5py

    sizes: list[int] = []
    for p in (shards / "shards").glob("*.h5"):
        with h5py.File(p, "r") as f:
            f.visititems(lambda name, obj: sizes.append(obj.id.get_storage_size())
                         if isinstance(obj, h5py.Dataset) and name not in ("rgba", "png", "jpeg", "masks") else None)
    return sum(sizes)


DYNACAP_CAMERAS, DYNACAP_FRAMES = 101, 18_700
"""A full DynaCap subject (docs/scale.md)."""
RAW_IMAGE_BYTES = WIDTH * HEIGHT * 4
"""An uncompressed RGBA image: the upper bound of the raw codec's bytes per image."""


def extrapolate(scale: dict, workers: tuple[int, ...] = (1, 32, 10, 100)) -> list[str]:
    """Markdown: a full DynaCap subject's shards, disk and wall time on ``workers`` one-core workers, from
    a bench run (``bench_out/paper_capture/scale.json``): its CPU cost model, and its wall-clock rate here."""
    model, full = scale["model"], scale["full"]
    frames, images = DYNACAP_FRAMES, DYNACAP_CAMERAS * DYNACAP_FRAMES
    geometry = scale["geometry_bytes"] / full["frames_converted"]
    image = (full["bytes_total"] - scale["geometry_bytes"]) / full["images_converted"]  # incl. meta.h5 share
    cpu = frames * model["per_frame"] + images * model["per_image"]
    wall_rate = full["images_converted"] / (full["seconds"] - full["seconds_setup"])
    shards = -(-frames // SHARD_FRAMES)
    tib = 1 << 40
    lines = [f"- {images:,} images, {shards:,} shards of {SHARD_FRAMES} frames x {DYNACAP_CAMERAS} cameras",
             f"- CPU: {cpu / 3600:,.1f} core-hours ({frames * model['per_frame'] / 3600:,.1f} h per-frame geometry, "
             f"{images * model['per_image'] / 3600:,.1f} h images); at this machine's wall-clock rate "
             f"({wall_rate:.1f} images/s per process) {images / wall_rate / 3600:,.1f} h",
             f"- disk: {frames * geometry / tib:.2f} TiB geometry + {images * image / tib:.2f} TiB images at the "
             f"synthetic capture's {image / 2**20:.2f} MiB per image; a shard "
             f"{(SHARD_FRAMES * geometry + SHARD_FRAMES * DYNACAP_CAMERAS * image) / 2**20:,.0f} MiB",
             "", "| workers (1 core each) | wall time, CPU model | wall time, this machine's rate |", "|---|---|---|"]
    for w in workers:
        used = min(w, shards)
        hours = (cpu / used + model["setup"]) / 3600
        here = (images / wall_rate / used + model["setup"]) / 3600
        lines.append(f"| {w} | {hours:,.2f} h | {here:,.2f} h |")
    return lines


if __name__ == "__main__":
    print("\n".join(extrapolate(json.loads((CAPTURE_DIR / "scale.json").read_text()))))
