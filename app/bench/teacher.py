"""`repaint-nerf bench teacher`: feature-teacher quality (driver; the measurement is core/bench/teacher.py).

On the synthetic presets (or a scene with ground truth): patch-query mask IoU across views, time and
storage per image. On a real photograph (matplotlib's bundled grace_hopper.jpg unless --photo): the mask a
patch on the jacket gives for each teacher (the built-in one plus every --teacher), its area fraction, and
a picture of the masks.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np

HELP = ("feature-teacher quality: patch-query mask IoU against ground truth on presets, and the mask a patch "
        "gives on a real photograph, per teacher; time and storage per image")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.core.bench.teacher import PRESETS

    p.add_argument("--preset", action="append", choices=PRESETS, help="synthetic preset (repeatable; default: all)")
    p.add_argument("--scene", default=None, help="a scene folder with gt/ masks (instead of generated presets)")
    p.add_argument("--no-presets", action="store_true", help="only the photograph")
    p.add_argument("--size", type=int, default=128, help="image size of generated presets")
    p.add_argument("--views", type=int, default=16, help="training views of generated presets")
    p.add_argument("--object", type=int, default=None, help="object id (default: gt/objects.json edited_object_id)")
    p.add_argument("--teacher", action="append", default=[], metavar="MODEL",
                   help="another feature teacher to measure besides the built-in one (repeatable): an ONNX file, a "
                        "transformers folder or a model id in the local Hugging Face cache")
    p.add_argument("--photo", default=None,
                   help="a photograph (default: matplotlib's sample_data/grace_hopper.jpg; 'none' to skip)")
    p.add_argument("--photo-patch", default=None, metavar="x0,y0,x1,y1",
                   help="the patch on the photograph as image fractions (default: on the jacket of grace_hopper.jpg)")
    p.add_argument("--sam-path", default=None, metavar="MODEL",
                   help="also refine each photo mask with this SAM (folder or cached model id)")
    p.add_argument("--json", default="bench_teacher.json", help="output JSON path")
    p.add_argument("--png", default=None, help="output PNG of preset similarity maps (default: beside the JSON); "
                                               "the photo's picture goes beside it as *_photo.png")


def sample_photo() -> Path:
    """matplotlib's bundled photograph of Grace Hopper."""
    import matplotlib

    return Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"


def _teachers(models: list[str]) -> list:
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher
    from repaint_nerf.core.teachers.stage1_targets import DEFAULT_FEATURE, FeatureModel, make_feature_teacher

    out = [DefaultFeatureTeacher()]
    for m in models:
        if m != DEFAULT_FEATURE:
            t = make_feature_teacher(FeatureModel(m))
            t.label = m
            out.append(t)
    return out


def _label(teacher) -> str:
    return getattr(teacher, "label", None) or teacher.name


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.bench.teacher import JACKET_PATCH, evaluate_scene
    from repaint_nerf.core.device import describe
    from repaint_nerf.core.errors import UserError

    out = Path(args.json)
    png = Path(args.png) if args.png else out.with_suffix(".png")
    teachers = _teachers(args.teacher)
    results: dict = {}
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_teacher_") as tmp:
        items = []
        if args.scene:
            if not (Path(args.scene) / "gt" / "objects.json").is_file():
                raise UserError("scene has no gt/objects.json (ground-truth masks are needed)", args.scene,
                                "use a scene written by `repaint-nerf make-scene`")
            items = [(Path(args.scene).name, Path(args.scene))]
        elif not args.no_presets:
            from repaint_nerf.core.bench.teacher import PRESETS
            from repaint_nerf.core.synth.generate import make_scene

            items = [(p, make_scene(p, Path(tmp) / p, size=args.size, views=args.views, seed=0, test_views=1))
                     for p in (args.preset or PRESETS)]
        for name, root in items:
            for k, teacher in enumerate(teachers):
                res, maps = evaluate_scene(root, Path(tmp) / f"cache_{name}_{k}", args.object, teacher)
                results.setdefault(_label(teacher), {})[name] = res
                rows.append(picture_row(**maps))
                print(f"{name:9s} {_label(teacher)[:24]:24s} iou@{res['threshold']:.2f}={res['iou']:.3f} "
                      f"best={res['best_iou']:.3f}@{res['best_threshold']:.2f} compressed={res['iou_compressed']:.3f} "
                      f"{res['ms_per_image']:.0f} ms/img {res['mb_per_image_504x378']:.2f} MB/img@504x378")
    photo = None if args.photo == "none" else Path(args.photo) if args.photo else sample_photo()
    photo_res = None
    if photo is not None:
        rect = JACKET_PATCH if args.photo_patch is None else _fractions(args.photo_patch)
        photo_res, photo_rows = run_photo(photo, rect, teachers, args.sam_path)
        photo_png = png.with_name(png.stem + "_photo.png")
        photo_png.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(photo_png), np.concatenate(photo_rows, 0)[..., ::-1])
        print(f"wrote {photo_png}")
    default = results.get(_label(teachers[0]), {})
    summary = {}
    if default:
        summary.update(min_iou=min(r["iou"] for r in default.values()),
                       min_iou_compressed=min(r["iou_compressed"] for r in default.values()))
    if photo_res:
        summary["photo_area_fraction"] = {k: v["area_fraction"] for k, v in photo_res["teachers"].items()}
    doc = {"benchmark": "teacher", "device": describe(), "teachers": [_label(t) for t in teachers],
           "summary": summary, "presets": results, "photo": photo_res,
           "timing_note": "CPU wall-clock on a shared machine: rough"}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    if rows:
        cv2.imwrite(str(png), np.concatenate([_pad(r, max(x.shape[1] for x in rows)) for r in rows], 0)[..., ::-1])
        print(f"wrote {png}")
    print(f"wrote {out}")
    return 0


def _fractions(text: str) -> tuple[float, float, float, float]:
    from repaint_nerf.core.errors import UserError

    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"--photo-patch '{text}' is not four fractions x0,y0,x1,y1",
                        hint="e.g. --photo-patch 0.12,0.88,0.22,0.96") from None
    if not (0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1):
        raise UserError(f"--photo-patch '{text}' is not a rectangle inside [0, 1]", hint="keep 0 <= x0 < x1 <= 1")
    return x0, y0, x1, y1


def run_photo(photo: Path, rect, teachers: list, sam_path: str | None = None) -> tuple[dict, list[np.ndarray]]:
    """Each teacher's mask from the patch `rect` (fractions) on the photograph: figures and picture rows."""
    from repaint_nerf.core.bench.teacher import evaluate_photo, patch_box
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.teachers.feature_default import DEFAULT_THRESHOLD

    bgr = cv2.imread(str(photo), cv2.IMREAD_COLOR)
    if bgr is None:
        raise UserError("cannot read the photograph", photo, hint="pass a JPEG or PNG file to --photo")
    rgb = bgr[..., ::-1].copy()
    box = patch_box(rect, *rgb.shape[:2])
    refine = None
    if sam_path:
        from repaint_nerf.core.models.sam import load_sam
        from repaint_nerf.core.teachers.sam_refine import refine_masks

        sam = load_sam(sam_path)
        refine = lambda masks: refine_masks([rgb], masks, sam)  # noqa: E731
    res, rows = {}, []
    for teacher in teachers:
        r, maps = evaluate_photo(rgb, box, teacher, DEFAULT_THRESHOLD, refine)
        res[_label(teacher)] = r
        rows.append(photo_row(_label(teacher), r, **maps))
        extra = f", SAM-refined {100 * r['area_fraction_refined']:.1f}%" if "area_fraction_refined" in r else ""
        print(f"photo {photo.name} {_label(teacher)[:40]:40s} mask@{r['threshold']:.2f} covers "
              f"{100 * r['area_fraction']:.1f}% of the image{extra} ({r['seconds']:.2f} s)")
    return {"photo": str(photo), "patch_fractions": list(rect), "teachers": res,
            "note": "only the built-in teacher's figures mean anything unless --teacher names real weights"}, rows


def photo_row(label: str, res: dict, image, sim, mask, box, refined=None, height: int = 300) -> np.ndarray:
    """Photo with the patch | similarity | mask over the photo (| SAM-refined mask), labelled, RGB uint8."""
    y0, y1, x0, x1 = box
    img = image.copy()
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (255, 255, 0), 3)
    simc = cv2.applyColorMap((np.clip(sim, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
    tiles = [img, simc, _overlay(image, mask)] + ([_overlay(image, refined)] if refined is not None else [])
    scale = height / image.shape[0]
    size = (int(round(image.shape[1] * scale)), height)
    row = np.concatenate([cv2.resize(np.ascontiguousarray(t), size, interpolation=cv2.INTER_AREA) for t in tiles], 1)
    text = f"{label[-60:]}: mask@{res['threshold']:.2f} covers {100 * res['area_fraction']:.1f}% of the image"
    if "area_fraction_refined" in res:
        text += f"; SAM-refined {100 * res['area_fraction_refined']:.1f}%"
    strip = np.full((26, row.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, row], 0)


def _overlay(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The photo tinted green where the mask is on and dimmed to grey where it is off."""
    img = image.astype(np.float32)
    grey = np.repeat(img.mean(-1, keepdims=True), 3, -1) * 0.4
    on = img * 0.45 + np.array([0, 255, 0], np.float32) * 0.55
    return np.clip(np.where(np.asarray(mask, bool)[..., None], on, grey), 0, 255).astype(np.uint8)


def picture_row(images, sims, gts, threshold, view, box, n: int = 4) -> np.ndarray:
    """Image | similarity | mask (green = hit, red = miss, blue = false) for a few views, RGB uint8."""
    from repaint_nerf.core.bench.teacher import teacher_input

    picks = [view] + [i for i in np.linspace(0, len(images) - 1, n).round().astype(int) if i != view][:n - 1]
    tiles = []
    for i in picks:
        img = teacher_input(images[i]).copy()
        if i == view:
            y0, y1, x0, x1 = box
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (255, 255, 0), 1)
        sim = cv2.applyColorMap((np.clip(sims[i], 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
        m = sims[i] > threshold
        err = np.zeros_like(img)
        err[m & gts[i]] = (40, 200, 40)
        err[~m & gts[i]] = (220, 40, 40)
        err[m & ~gts[i]] = (40, 80, 230)
        tiles += [img, sim, err]
    return np.concatenate(tiles, 1)


def _pad(row: np.ndarray, width: int) -> np.ndarray:
    return np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)))
