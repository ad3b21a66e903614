"""Stability: sweep what breaks deformable light-field avatars and chart where each variant fails.

Usage: ``python -m recipes.stability --out OUT [--quick] [--seeds N] [--subject DIR | --shards DIR]
[--variants single_surface,two_surface] [--fail-db 1.0]``.

Sweeps (each configuration trained with the same iterations, L1 only, with ``--seeds N`` training seeds,
default 3 in full mode, evaluated on held-out cameras; every number is the mean ± std over the seeds in
foreground PSNR/SSIM/FLIP inside the person's padded mask box, the official protocol's PSNR beside it):

* ``offset``: outer-shell offset d in mm, the plain shell (``ConvertConfig(offset_mm=d)``, every vertex
  moved by d) and the safe shell (``TemplateConfig(offset_mm=d, safe=True)``, d limited per vertex
  where the shell would cross another body part; converted with ``--template``). At d = 0 both
  shells are the inner surface, so the safe row repeats the plain one.
* ``smoothing``: Taubin iterations of the template's ``smooth`` variant (0 = the original).
* ``cameras``: number of training cameras (a spread subset, converted with ``--cameras``; the
  held-out cameras stay the same).
* ``pose_distance``: the base models (30 mm, original template, all cameras) evaluated frame by
  frame on the held-out cameras, on training poses (distance 0) and on the test motion, binned by the
  distance of each test pose to the nearest training pose: the Euclidean norm over every DOF but
  the first three (the Skeletool root translation, which moves the body without changing how it
  looks), in DOF units (radians times the skeleton's DOF weights). The root rotation counts: the
  normal maps, and the synthetic captures' lighting, are in world space.
* ``holes``: the template with holes (faces within two rings of k random vertices deleted, so it is
  not watertight). Depth peeling needs the shell's exit hit where a ray misses the inner surface;
  the row reports the fraction of shell-hitting rays without an exit hit, the fraction of them
  that are then not shaded at all, and the PSNR.

A row *fails* when it raised an error, its foreground PSNR (mean over seeds) is not finite, or it is
more than ``--fail-db`` below the best of the same variant in the same sweep. Errors are recorded, never fatal.
Writes ``results.json``, ``results.md`` and one chart per sweep (``stability_<sweep>.png``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from recipes.common import (RecipeSizes, find_character, prepare_capture, prepare_shards, prepare_template_variants,
                            recipe_parser, seed_list, shards_source, sizes_from_args, train_and_eval_seeds)
from recipes.seeds import train_seeds
from recipes.stability_report import HEADLINE, mark_failures, markdown, sweep_chart

logger = logging.getLogger(__name__)

SWEEPS = ("offset", "smoothing", "cameras", "pose_distance", "holes")
ROOT_TRANSLATION_DOFS = 3
"""Skeletool skeletons start with the root's translate_x/y/z DOFs (then its rotate_y/z/x)."""
HOLE_RINGS = 2


@dataclass(frozen=True)
class StabilityPlan:
    """Values of each sweep."""

    offsets_mm: tuple[float, ...]
    smooth_iters: tuple[int, ...]
    train_cameras: tuple[int, ...]
    """Training-camera counts below the capture's (which is always added as "all")."""
    pose_bins: int
    """Equal-count bins of the test frames by pose distance."""
    holes: tuple[int, ...]
    """Number of holes punched into the template (0 = the original)."""

    @staticmethod
    def for_mode(quick: bool) -> "StabilityPlan":
        if quick:
            return StabilityPlan(offsets_mm=(0.0, 30.0), smooth_iters=(0, 30), train_cameras=(2,), pose_bins=2,
                                 holes=(0, 6))
        return StabilityPlan(offsets_mm=(0.0, 5.0, 15.0, 30.0, 60.0, 100.0), smooth_iters=(0, 10, 50, 200),
                             train_cameras=(4, 6), pose_bins=4, holes=(0, 2, 8, 32))


class _Study:
    """Shared state: capture, base shards, cached conversions and trained runs."""

    def __init__(self, args, sizes: RecipeSizes, out: Path, subject: Path, base: Path, source: dict, variants):
        self.args, self.sizes, self.out, self.subject, self.base = args, sizes, out, subject, base
        self.source = source
        self.variants = variants
        self.jobs = 1 if args.quick else 2
        self.seeds = seed_list(args)
        self.character = Path(source["character"]) if source.get("character") else find_character(subject)
        self.base_offset = float(source.get("offset_mm", 30.0))
        self.base_template = source.get("template")
        self._shards: dict[str, Path | Exception] = {"base": base}
        self._runs: dict[tuple[str, str], dict] = {}

    def shards(self, key: str, make: Callable[[], Path]) -> Path:
        """Shards ``key`` (made once by ``make``); a failed conversion raises again for every user."""
        if key not in self._shards:
            try:
                self._shards[key] = make()
            except Exception as exc:
                logger.exception("shards %s failed", key)
                self._shards[key] = exc
        value = self._shards[key]
        if isinstance(value, Exception):
            raise value
        return value

    def convert(self, key: str, template: str | None = None, offset_mm: float | None = None,
                cameras: list[int] | None = None) -> Path:
        return self.shards(key, lambda: prepare_shards(
            self.out, self.subject, self.sizes, name=f"shards_{key}",
            template=template if template is not None else self.base_template,
            offset_mm=self.base_offset if offset_mm is None else offset_mm, cameras=cameras, jobs=self.jobs))

    def run(self, key: str, variant: str, shards: Callable[[], Path]) -> dict:
        """Train + evaluate ``variant`` on shards ``key`` once per seed (``runs/KEY/VARIANT/seed<S>``); an
        error becomes a row with ``error``."""
        if (key, variant) not in self._runs:
            name = f"{key}/{variant}"
            try:
                row = train_and_eval_seeds(name, shards(), self.out / "runs" / key / variant, self.sizes, variant,
                                           self.seeds, self.args.device, extra_splits=False)
                row["run_dir"] = str(self.out / "runs" / key / variant)
            except Exception as exc:  # one broken configuration never stops the study
                logger.exception("%s failed", name)
                print(f"  {name}: ERROR {type(exc).__name__}: {exc}", flush=True)
                row = _error(exc)
            self._runs[(key, variant)] = row
        return dict(self._runs[(key, variant)])


def _error(exc: BaseException) -> dict:
    return {"psnr": None, "ssim": None, "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(limit=6)}


_KEEP = ("psnr", "ssim", "lpips", "num_parameters", "stage_ms", "fps", "frames", "images", "error", "traceback",
         "train_s", "run_dir", "seeds", "per_seed", "stats", "fg_psnr_mean", "fg_ssim_mean", "fg_flip_mean",
         "psnr_mean")


def _row(sweep: str, series: str, value: float, label: str, variant: str, result: dict, **extra) -> dict:
    row = {"sweep": sweep, "series": series, "value": float(value), "label": label, "variant": variant,
           "name": f"{sweep} {label} {variant}" + (f" ({series})" if series else "")}
    row.update({k: result.get(k) for k in _KEEP if k in result})
    row.setdefault("error", None)
    row.update(extra)
    return row


# ------------------------------------------------------------------------------------------------ sweeps
def sweep_offset(st: _Study, plan: StabilityPlan) -> list[dict]:
    from deliffas.data.template_build import TemplateConfig, build_templates

    rows = []
    for d in plan.offsets_mm:
        plain_key = f"offset{d:g}"
        stats = _plain_shell_stats(st.character, d)
        for v in st.variants:
            rows.append(_row("offset", "plain", d, f"{d:g} mm", v,
                             st.run(plain_key, v, lambda: st.convert(plain_key, offset_mm=d)), shell=stats))
        if d == 0:  # nothing to limit: the safe shell is the inner surface too
            for v in st.variants:
                rows.append(_row("offset", "safe", d, f"{d:g} mm", v,
                                 st.run(plain_key, v, lambda: st.convert(plain_key, offset_mm=d)),
                                 shell=stats, note="d = 0: identical to the plain shell"))
            continue
        key = f"safe{d:g}"
        report: dict = {}

        def make(d=d, key=key, report=report) -> Path:
            folder = st.out / "templates" / key
            if not (folder / "report.json").is_file():
                build_templates(TemplateConfig(st.character, folder, offset_mm=d, safe=True,
                                               atlas_res=128 if st.args.quick else 512))
            report.update(json.loads((folder / "report.json").read_text())["variants"]["original"]["shell"])
            return prepare_shards(st.out, st.subject, st.sizes, name=f"shards_{key}", template=str(folder / "original"),
                                  jobs=st.jobs)

        for v in st.variants:
            result = st.run(key, v, lambda: st.shards(key, make))
            rows.append(_row("offset", "safe", d, f"{d:g} mm", v, result, shell=_shell_summary(report) or None))
    return rows


def _shell_summary(report: dict) -> dict:
    keys = ("num_self_intersecting_faces", "num_clamped", "offset_min_mm", "offset_mean_mm", "watertight")
    return {k: report[k] for k in keys if k in report}


def _plain_shell_stats(character: Path, d: float) -> dict | None:
    """Rest-pose statistics of the plain shell at d (self-intersecting faces), None if they fail."""
    try:
        from deliffas.io.formats.dynacap.character import read_character
        from deliffas.geometry.shell import offset_shell, shell_report

        mesh = read_character(character).mesh
        verts = np.asarray(mesh.verts, np.float64)
        outer = offset_shell(verts, mesh.faces, np.full(len(verts), float(d)))
        return _shell_summary(dataclasses.asdict(shell_report(verts, mesh.faces, outer)))
    except Exception as exc:
        logger.warning("shell statistics at d=%s failed: %s", d, exc)
        return None


def sweep_smoothing(st: _Study, plan: StabilityPlan) -> list[dict]:
    rows = []
    for k in plan.smooth_iters:
        if k == 0:
            key, make = "base", (lambda: st.base)
        else:
            key = f"smooth{k}"

            def make(k=k, key=key) -> Path:
                folders = prepare_template_variants(st.out / "templates" / key, st.character, smooth_iters=k,
                                                    offset_mm=st.base_offset, packing_res=128 if st.args.quick else 512)
                return st.convert(key, template=str(folders["smooth"]))
        for v in st.variants:
            rows.append(_row("smoothing", "", k, f"{k} iterations", v, st.run(key, v, make)))
    return rows


def sweep_cameras(st: _Study, plan: StabilityPlan) -> list[dict]:
    from deliffas.data.shards import ShardSet

    meta = ShardSet(st.base).meta
    train = sorted(int(c) for c in meta.train_cameras)
    test = sorted(int(c) for c in meta.test_cameras)
    rows = []
    counts = sorted({c for c in plan.train_cameras if 1 <= c < len(train)}) + [len(train)]
    for n in counts:
        if n == len(train):
            key, make, subset = "base", (lambda: st.base), train
        else:
            subset = [train[int((i + 0.5) * len(train) / n)] for i in range(n)]
            key = f"cameras{n}"
            make = (lambda key=key, subset=subset: st.convert(key, cameras=sorted(subset + test)))
        label = f"{n} cameras" + (" (all)" if n == len(train) else "")
        for v in st.variants:
            rows.append(_row("cameras", "", n, label, v, st.run(key, v, make), train_cameras=subset,
                             test_cameras=test))
    return rows


def _sequence_dofs(shards: Path, sequence: str) -> tuple[list[int], np.ndarray]:
    """Capture frames of ``sequence`` and their (N, D) motion DOFs, read from the shards' geometry."""
    from deliffas.data.shards import ShardSet

    ss = ShardSet(shards)
    frames = [int(f) for f in ss.frames(sequence)]
    dofs = []
    for f in frames:
        shard, row = ss.locate(sequence, f)
        r0 = int(shard.h5["window_rows"][row][0])
        dofs.append(np.asarray(shard.geometry("dofs", [r0])[0], np.float64))
    return frames, np.stack(dofs)


def pose_distances(shards: Path) -> dict[int, float]:
    """Test frame -> distance of its DOFs (root translation left out) to the nearest training frame's."""
    _, train = _sequence_dofs(shards, "training")
    frames, test = _sequence_dofs(shards, "testing")
    a, b = test[:, ROOT_TRANSLATION_DOFS:], train[:, ROOT_TRANSLATION_DOFS:]
    dist = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min(1)
    return {f: float(x) for f, x in zip(frames, dist)}


def _per_frame_metrics(run_dir: Path, shards: Path, split: str, max_frames: int | None, evaluator) -> dict[int, list]:
    """Protocol metrics of every held-out-camera image of ``split``'s frames (frame -> ``ImageMetrics`` list).

    Frames come from ``evaluation_samples`` under protocol ``all`` (every converted frame, at most
    ``max_frames`` evenly spaced); only the held-out cameras are rendered.
    """
    import torch

    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.runs import load_run
    from deliffas.engine.shading import render_frame
    from deliffas.engine.samples import composite_target
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    model, _ = load_run(run_dir)
    samples, info = evaluation_samples(str(shards), split, max_frames=max_frames, with_rays=False, protocol="all",
                                       temporal_window=model.config.temporal_window)
    held_out = set(info["test_cameras"])
    out: dict[int, list] = {}
    for sample in samples:
        keep = [k for k, c in enumerate(sample.camera_ids) if int(c) in held_out]
        if not keep:
            continue
        sample = dataclasses.replace(sample, images=sample.images[keep], masks=sample.masks[keep],
                                     cameras=[sample.cameras[k] for k in keep], camera_ids=sample.camera_ids[keep])
        caster = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
        preds = render_frame(model, sample, caster, torch.device("cpu"), StageTimer("cpu"))
        gt = composite_target(sample.images, sample.masks)
        out[sample.frame] = [evaluator.add(preds[k].permute(2, 0, 1), gt[k].permute(2, 0, 1),
                                           torch.as_tensor(sample.masks[k]).float()) for k in range(len(keep))]
    return out


def _mean_metrics(records: list) -> dict:
    """Mean official PSNR / SSIM and ``foreground`` block of ``ImageMetrics`` records, shaped like an
    evaluation (None when there are none or a metric is unavailable)."""
    def avg(field):
        values = [getattr(m, field) for m in records]
        return float(np.mean(values)) if values and all(v is not None for v in values) else None

    return {"psnr": avg("psnr"), "ssim": avg("ssim"), "images": len(records),
            "foreground": {"psnr": avg("fg_psnr"), "ssim": avg("fg_ssim"), "flip": avg("fg_flip"),
                           "masked_psnr": avg("masked_psnr")}}


def sweep_pose_distance(st: _Study, plan: StabilityPlan) -> list[dict]:
    from deliffas.models.metrics import Evaluator

    dist = pose_distances(st.base)
    order = sorted(dist, key=dist.get)
    bins = [list(b) for b in np.array_split(np.asarray(order), min(plan.pose_bins, len(order))) if len(b)]
    evaluator = Evaluator()
    rows = []
    for v in st.variants:
        base = st.run("base", v, lambda: st.base)
        if base.get("error"):
            rows.append(_row("pose_distance", "", 0.0, "training poses", v, base))
            continue
        try:
            # every seed's run scored frame by frame once; each row is then the mean ± std over seeds
            seen = {s: _per_frame_metrics(Path(base["run_dir"]) / f"seed{s}", st.base, "novel_view",
                                          st.sizes.eval_frames, evaluator) for s in st.seeds}
            novel = {s: _per_frame_metrics(Path(base["run_dir"]) / f"seed{s}", st.base, "novel_pose", None, evaluator)
                     for s in st.seeds}

            def over_seeds(name, pick):
                return train_seeds(name, st.seeds, base["run_dir"],
                                   lambda seed, _run: (_mean_metrics(pick(seed)), None, None))

            first = seen[st.seeds[0]]
            rows.append(_row("pose_distance", "", 0.0, "0 (training poses)", v,
                             {**over_seeds(v, lambda s: [m for ms in seen[s].values() for m in ms]),
                              "frames": len(first)}, distance=0.0, test_frames=sorted(first)))
            for b in bins:
                frames = [int(f) for f in b]
                mean_d = float(np.mean([dist[f] for f in frames]))
                result = over_seeds(v, lambda s, frames=frames: [m for f in frames for m in novel[s].get(f, [])])
                rows.append(_row("pose_distance", "", mean_d, f"{mean_d:.3g}", v, {**result, "frames": len(frames)},
                                 distance=mean_d, distance_range=[min(dist[f] for f in frames),
                                                                  max(dist[f] for f in frames)], test_frames=frames))
        except Exception as exc:
            logger.exception("pose distance of %s failed", v)
            rows.append(_row("pose_distance", "", 0.0, "n/a", v, _error(exc)))
    return rows


def holed_template(character: Path, folder: Path, holes: int, seed: int = 0, rings: int = HOLE_RINGS) -> dict:
    """Write ``character`` with the faces within ``rings`` rings of ``holes`` random vertices deleted.

    Vertices stay (the template's vertex order and skinning are untouched); vertices left without a
    face get no normal and stay in place in the shell. Returns ``{"character", "faces_deleted",
    "faces", "boundary_edges"}``.
    """
    from deliffas.io.formats.dynacap.character import read_character
    from deliffas.geometry.shell import boundary_edges
    from deliffas.geometry.variants import write_variant

    char = read_character(character)
    mesh = char.mesh
    faces = np.asarray(mesh.faces, np.int64)
    used = np.unique(faces)
    rng = np.random.default_rng(seed)
    region = np.zeros(mesh.num_verts, bool)
    region[rng.choice(used, size=min(holes, len(used)), replace=False)] = True
    for _ in range(rings - 1):
        touch = region[faces].any(1)
        region[faces[touch].ravel()] = True
    drop = region[faces].any(1)
    keep = ~drop
    new_mesh = dataclasses.replace(
        mesh, faces=faces[keep],
        face_uvs=None if mesh.face_uvs is None else np.asarray(mesh.face_uvs)[keep],
        face_normals_idx=None if getattr(mesh, "face_normals_idx", None) is None
        else np.asarray(mesh.face_normals_idx)[keep])
    path = write_variant(folder, dataclasses.replace(char, mesh=new_mesh), "holes")
    return {"character": str(path), "faces_deleted": int(drop.sum()), "faces": int(keep.sum()),
            "boundary_edges": int(len(boundary_edges(faces[keep])))}


def exit_hit_stats(shards: Path, max_frames: int | None) -> dict:
    """Over the held-out cameras of the training frames: rays meeting the shell, the fraction of
    them without a peeled exit hit, the fraction not shaded at all (no inner hit and no exit), and
    the fraction of person pixels (mask > 0.5) left unshaded."""
    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.geometry.raycast import UVRaycaster

    samples, info = evaluation_samples(str(shards), "novel_view", max_frames=max_frames, protocol="all")
    outer = no_exit = dropped = person = person_unshaded = 0
    for s in samples:
        caster = UVRaycaster(s.inner_verts, info["faces"], s.outer_verts, info["atlas"])
        for k, cam in enumerate(s.cameras):
            h = caster.cast(cam)
            shaded = h.outer_hit & (h.inner_hit | h.outer_exit_hit)
            outer += int(h.outer_hit.sum())
            no_exit += int((h.outer_hit & ~h.outer_exit_hit).sum())
            dropped += int((h.outer_hit & ~shaded).sum())
            m = s.masks[k] > 0.5
            person += int(m.sum())
            person_unshaded += int((m & ~shaded).sum())
    return {"rays_hitting_shell": outer, "no_exit_fraction": no_exit / max(outer, 1),
            "unshaded_fraction": dropped / max(outer, 1), "person_unshaded_fraction": person_unshaded / max(person, 1)}


def sweep_holes(st: _Study, plan: StabilityPlan) -> list[dict]:
    rows = []
    for n in plan.holes:
        info: dict = {}
        if n == 0:
            key, make = "base", (lambda: st.base)
            info.update(faces_deleted=0)
        else:
            key = f"holes{n}"

            def make(n=n, key=key, info=info) -> Path:
                info.update(holed_template(st.character, st.out / "templates" / key, n, seed=st.args.seed))
                return st.convert(key, template=str(st.out / "templates" / key))
        try:
            stats = exit_hit_stats(st.shards(key, make), st.sizes.eval_frames)
        except Exception as exc:
            logger.exception("exit-hit statistics with %d holes failed", n)
            stats = {"exit_stats_error": f"{type(exc).__name__}: {exc}"}
        for v in st.variants:
            rows.append(_row("holes", "", n, f"{n} holes", v, st.run(key, v, make), **info, **stats))
    return rows


SWEEP_FUNCS = {"offset": sweep_offset, "smoothing": sweep_smoothing, "cameras": sweep_cameras,
               "pose_distance": sweep_pose_distance, "holes": sweep_holes}
# ------------------------------------------------------------------------------------------------ main
def _parser():
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    p.add_argument("--variants", default="single_surface,two_surface", help="comma-separated zoo names")
    p.add_argument("--fail-db", type=float, default=1.0, help="a row fails below (sweep best - this) dB foreground PSNR")
    p.add_argument("--sweeps", default=",".join(SWEEPS), help=f"comma-separated subset of {','.join(SWEEPS)}")
    p.add_argument("--plan", choices=["auto", "quick", "full"], default="auto",
                   help="swept values: quick (a couple per sweep) or full; auto follows --quick")
    return p


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    sizes = sizes_from_args(args)
    plan = StabilityPlan.for_mode(args.quick if args.plan == "auto" else args.plan == "quick")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    sweeps = [s.strip() for s in args.sweeps.split(",") if s.strip()]
    unknown = sorted(set(sweeps) - set(SWEEPS))
    if unknown:
        raise SystemExit(f"stability: unknown sweeps {unknown} (known: {list(SWEEPS)})")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    jobs = 1 if args.quick else 2
    if args.shards:
        base = Path(args.shards)
        source = shards_source(base)
        subject = Path(args.subject or source.get("subject"))
        sizes = dataclasses.replace(sizes, atlas_res=int(source.get("atlas_res", sizes.atlas_res)))
    else:
        subject = prepare_capture(out, sizes, args.seed, args.subject, jobs=jobs)
        base = prepare_shards(out, subject, sizes, jobs=jobs)
        source = shards_source(base)
    st = _Study(args, sizes, out, subject, base, source, variants)
    rows: list[dict] = []
    for sweep in sweeps:
        print(f"sweep {sweep}", flush=True)
        try:
            rows += SWEEP_FUNCS[sweep](st, plan)
        except Exception as exc:  # a whole sweep failing is recorded once per variant
            logger.exception("sweep %s failed", sweep)
            rows += [_row(sweep, "", 0.0, "sweep failed", v, _error(exc)) for v in variants]
    summary = mark_failures(rows, args.fail_db)
    title = "Stability" + (" — quick mode" if args.quick else "")
    charts = {}
    for sweep in dict.fromkeys(r["sweep"] for r in rows):
        charts[sweep] = str(sweep_chart([r for r in rows if r["sweep"] == sweep], sweep, out / f"stability_{sweep}.png",
                                        f"{title}: {sweep}", args.fail_db))
    payload = {"title": title, "quick": args.quick, "sizes": dataclasses.asdict(sizes),
               "plan": dataclasses.asdict(plan),
               "variants": variants, "fail_db": args.fail_db,
               "seeds": st.seeds, "metric": HEADLINE,
               "fail_rule": f"error, non-finite foreground PSNR (mean over seeds), or more than {args.fail_db:g} dB "
                            "below the best of the same variant in the same sweep",
               "failures": summary, "charts": charts, "results": rows, "command": " ".join(sys.argv)}
    (out / "results.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    md = [f"# {title}", "", f"Preset {sizes.preset}, {sizes.iters} iterations per configuration and seed, L1 only, "
          f"seeds {st.seeds}; held-out cameras, mean ± std over the seeds; fg = inside the person's padded mask box "
          f"(the headline), official = the paper's protocol. A row fails: {payload['fail_rule']}.", "",
          *markdown(rows, summary, args.fail_db)]
    (out / "results.md").write_text("\n".join(md))
    print("\n".join(md))
    return payload


if __name__ == "__main__":
    main()
