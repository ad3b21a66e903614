"""The paper's data scale: conversion of a 1285 x 940, 8-camera, 30-frame capture at atlas S = 1024.

Rows: conversion images per CPU-second (one process, setup excluded; CPU time, so the figure is
per core whatever else runs on the shared machine, with the wall-clock rate beside it), its split
into set-up, a per-frame and a per-image cost (three runs: 8 cameras x 30 frames, 2 x 30, 8 x 10),
the peak resident set of a converting worker (one process; and each of a 2-worker LocalCluster),
shard bytes per frame and per image, and ``ShardDataset`` samples/s (K = 4 cameras) on the
shards. docs/scale.md extrapolates a full DynaCap subject from them. The capture is synthesized once into
``bench_out/paper_capture`` (deterministic, seed 0) and reused by later runs.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import Result

WIDTH, HEIGHT, CAMERAS, FRAMES, ATLAS = 1285, 940, 8, 30, 1024
"""The paper's image size (as bench_engine renders it), a DynaCap-like rig subset, its atlas side S."""
SHARD_FRAMES = 10
K = 4
WORKER_RSS_TARGET = 3 << 30
"""Peak resident set a converting worker must stay under at this size, bytes (independent of frames and cameras)."""
CAPTURE_DIR = Path(os.environ.get("DELIFFAS_PAPER_CAPTURE", "bench_out/paper_capture"))


def paper_capture() -> Path:
    """The synthetic subject at the paper's size (made once; ``capture.json`` records how)."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    record = {"width": WIDTH, "height": HEIGHT, "cameras": CAMERAS, "frames": FRAMES, "seed": 0}
    done = CAPTURE_DIR / "capture.json"
    if done.is_file() and json.loads(done.read_text()) == record:
        return CAPTURE_DIR / "subject"
    shutil.rmtree(CAPTURE_DIR, ignore_errors=True)
    CAPTURE_DIR.mkdir(parents=True)
    t0 = time.perf_counter()
    synthesize_capture(CAPTURE_DIR / "subject", SynthConfig(num_frames=FRAMES, num_test_frames=1, num_cameras=CAMERAS,
                                                            width=WIDTH, height=HEIGHT, seed=0))
    done.write_text(json.dumps({**record, "synth_seconds": time.perf_counter() - t0}))
    return CAPTURE_DIR / "subject"


def _probe(subject: Path, out: Path, **config) -> dict:
    """One conversion in a fresh process (benchmarks._convert_probe): timings and worker peak RSS."""
    shutil.rmtree(out, ignore_errors=True)
    cfg = {"atlas_res": ATLAS, "shard_frames": SHARD_FRAMES, "sequences": ["training"], **config}
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
    subject = paper_capture()
    work = CAPTURE_DIR / "out"
    full = _probe(subject, work / "all")
    two = _probe(subject, work / "two", cameras=[0, 1])
    third = _probe(subject, work / "third", frames="0:10")
    dask = _probe(subject, work / "dask", dask_workers=2)
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
        Result("scale", f"convert {WIDTH}x{HEIGHT}, {CAMERAS} cams, S={ATLAS}, per CPU-s", images / work_cpu,
               "images/s", note=f"per core (jobs 1, CPU time, setup excl.); {CAMERAS} cams x {FRAMES} frames"),
        Result("scale", "  the same, wall clock on this shared machine",
               images / (full["seconds"] - full["seconds_setup"]), "images/s", note=note),
        Result("scale", "  cost per frame (posing, surfaces, normal maps, stored)", model["per_frame"], "CPU s",
               note="from runs of 8 cams x 30 frames, 2 cams x 30, 8 cams x 10"),
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
        Result("scale", f"shard of {SHARD_FRAMES} frames x {CAMERAS} cams", float(np.mean(shard_bytes)) / mib, "MiB",
               note=f"{len(shards)} shards; {(sum(shard_bytes) - geometry_bytes) / images / mib:.3f} MiB per image "
                    f"(raw codec, synthetic), {geometry_bytes / full['frames_converted'] / mib:.1f} MiB geometry per "
                    f"frame"),
        Result("scale", f"ShardDataset S={ATLAS}, K={K} cams/item, 0 workers, per CPU-s", per_cpu, "samples/s"),
        Result("scale", "  the same, wall clock on this shared machine", wall, "samples/s", note=note),
    ]
    (CAPTURE_DIR / "scale.json").write_text(json.dumps({"full": full, "two_cameras": two, "ten_frames": third,
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
