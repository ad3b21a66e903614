"""The speed/accuracy front of docs/results.md: frames per second at 940 x 1285 against masked PSNR, per configuration.

Usage (runs trained beforehand, one configuration per ``NAME``, its runs the training seeds)::

    python -m benchmarks.front NAME=RUN[,RUN ...] ... --out DIR [--max-frames 10] [--rounds 3]

For each configuration: the masked and foreground PSNR of each run on the validation camera and on the test
cameras (``deliffas eval --split validation|novel_view --max-frames N``; mean and standard deviation over its runs),
and the fast path's frames per second at 940 x 1285 with a new pose every frame (normal maps to U-Nets, uvs and
shading per frame, two frames in flight on one torch thread each, as ``deliffas render`` streams), timed on its
first run: the first test frame's first camera rescaled, the best of ``--rounds`` rounds of 8 frames, the
configurations interleaved round by round. fps does not depend on the trained weights; it depends on the machine
(recorded in the outputs) and on the hidden layers' dtype (``--render-dtype``, default auto). The front: the
configurations no other beats in both fps and validation masked PSNR (choices are made on the validation camera).
Writes ``front.md``, ``front.json`` and ``front.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
from pathlib import Path


from benchmarks._timing import best_times, torch_threads

SIZE = (1285, 940)
"""(width, height) of the timed frame."""
FRAMES = 8
"""Frames per timed round."""
SPLITS = ("validation", "novel_view")
OUTPUTS = ("front.md", "front.json", "front.png")
"""What a run writes into ``--out``."""


def _scores(run: str, split: str, max_frames: int) -> dict[str, float]:
    from deliffas.engine.evaluate import EvalConfig, evaluate

    fg = evaluate(EvalConfig(run=run, split=split, max_frames=max_frames)).foreground
    return {"masked": float(fg.masked_psnr), "fg": float(fg.psnr)}


def _stream(run: str, dtype: str):
    """A function that renders :data:`FRAMES` frames of ``run`` at :data:`SIZE`, two in flight, everything per frame."""
    from benchmarks.preset_table import first_test_frame, new_pose_frame
    from deliffas.fast.config import RenderPathConfig
    from deliffas.fast.frame import render_stream

    model, sample, info = first_test_frame(run)
    frame = new_pose_frame(model, sample, info, sample.cameras[0].rescaled(*SIZE),
                           RenderPathConfig(dtype=dtype, project_features=False))

    def run_frames():
        for _ in render_stream(frame, range(FRAMES), 2):
            pass
    return run_frames


def _mean_std(values: list[float]) -> tuple[float, float]:
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def measure(configs: dict[str, list[str]], max_frames: int, rounds: int, dtype: str = "auto") -> list[dict]:
    """One row per configuration: its runs' scores per split (mean, std, per run) and its fps (hidden layers in
    ``dtype``, ``RenderPathConfig.dtype``)."""
    with torch_threads(1):
        t = best_times({name: _stream(runs[0], dtype) for name, runs in configs.items()}, repeat=rounds,
                       max_rounds=rounds)
    rows = []
    for name, runs in configs.items():
        row = {"name": name, "runs": runs, "fps": FRAMES / t[name]}
        for split in SPLITS:
            per_run = [_scores(run, split, max_frames) for run in runs]
            for key in ("masked", "fg"):
                mean, std = _mean_std([s[key] for s in per_run])
                row[f"{split}_{key}"], row[f"{split}_{key}_std"] = mean, std
                row[f"{split}_{key}_runs"] = [s[key] for s in per_run]
        rows.append(row)
    return rows


def mark_front(rows: list[dict]) -> None:
    """Set ``front`` on each row: True where no other row has both more fps and a higher validation masked PSNR."""
    from deliffas.engine.report import pareto_front

    front = set(pareto_front([-r["fps"] for r in rows], [r["validation_masked"] for r in rows]).tolist())
    for i, r in enumerate(rows):
        r["front"] = i in front


def markdown(rows: list[dict]) -> str:
    lines = ["| configuration | runs | fps at 940 x 1285 | validation masked | validation fg | test masked | test fg "
             "| on the front |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in sorted(rows, key=lambda r: -r["fps"]):
        cells = [f"{r[f'{s}_{k}']:.2f} ± {r[f'{s}_{k}_std']:.2f}" for s in SPLITS for k in ("masked", "fg")]
        lines.append(f"| {r['name']} | {len(r['runs'])} | {r['fps']:.1f} | " + " | ".join(cells)
                     + f" | {'yes' if r['front'] else ''} |")
    return "\n".join(lines)


def chart(rows: list[dict], path: Path) -> Path:
    from deliffas.engine.report import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.2, 4.8), dpi=120)
    keys = []
    for i, r in enumerate(sorted(rows, key=lambda r: -r["validation_masked"]), 1):  # numbered, named in a key
        ax.errorbar(r["fps"], r["validation_masked"], yerr=r["validation_masked_std"], fmt="o",
                    color="tab:red" if r["front"] else "tab:blue", capsize=3, zorder=3)
        ax.annotate(str(i), (r["fps"], r["validation_masked"]), textcoords="offset points", xytext=(5, 3), fontsize=8)
        keys.append(f"{i}  {r['name']}")
    ax.text(0.3, 0.25, "\n".join(keys), transform=ax.transAxes, fontsize=7, va="bottom",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.8"})
    front = sorted((r for r in rows if r["front"]), key=lambda r: r["fps"])
    if len(front) > 1:
        ax.plot([r["fps"] for r in front], [r["validation_masked"] for r in front], "--", color="tab:red",
                label="front", zorder=2)
        ax.legend(loc="center right")
    ax.set_xlabel("fps at 940 x 1285, a new pose every frame (2 frames in flight, 2 CPU threads)")
    ax.set_ylabel("masked PSNR (dB), validation camera")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def _cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo where there is one, else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("configs", nargs="+", help="NAME=RUN[,RUN ...]: a configuration and its runs (seeds)")
    parser.add_argument("--out", type=Path, required=True, help="folder for front.md, front.json and front.png")
    parser.add_argument("--max-frames", type=int, default=10, help="frames of each evaluation (default 10)")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds of 8 frames per configuration (default 3)")
    parser.add_argument("--render-dtype", choices=("auto", "float32", "bfloat16"), default="auto",
                        help="the fused pass's hidden layers (default auto: bf16 where the CPU has native bf16)")
    parser.add_argument("--overwrite", action="store_true", help="replace front.md, front.json and front.png in --out")
    args = parser.parse_args(argv)
    from deliffas.engine.train import RUN_MARKER

    args.parsed = {}
    for item in args.configs:
        name, sep, runs = item.partition("=")
        paths = [p for p in runs.split(",") if p]
        if not sep or not name or not paths or not all((Path(p) / RUN_MARKER).is_file() for p in paths):
            parser.error(f"{item!r}: expected NAME=RUN[,RUN ...], each RUN a run directory of `deliffas train` "
                         f"(with its {RUN_MARKER})")
        args.parsed[name] = paths
    written = [f for f in OUTPUTS if (args.out / f).exists()]
    if written and not args.overwrite:
        parser.error(f"{args.out}: holds {', '.join(written)}; pass --overwrite to replace them")
    return args


def main(argv: list[str] | None = None) -> list[dict]:
    args = _parse(argv)
    rows = measure(args.parsed, args.max_frames, args.rounds, args.render_dtype)
    mark_front(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    from deliffas.fast.config import RenderPathConfig
    from deliffas.fast.shade import mlp_dtype

    dtype = str(mlp_dtype(RenderPathConfig(dtype=args.render_dtype).dtype)).replace("torch.", "")
    machine = (f"{_cpu_name()}, {os.cpu_count()} CPUs, load "
               f"{os.getloadavg()[0]:.1f}, hidden layers in {dtype}")
    (args.out / "front.json").write_text(json.dumps({"machine": machine, "rows": rows}, indent=1))
    table = markdown(rows)
    (args.out / "front.md").write_text(table + f"\n\nMachine: {machine}.\n")
    chart(rows, args.out / "front.png")
    print(table)
    return rows


if __name__ == "__main__":
    main()
