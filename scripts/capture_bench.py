"""Benchmark of `boostnerf capture` (docs/capture.md): seconds per phase, poses against known ones, and a DVGO
mixture trained on capture's poses against the same recipe on known poses.

    python scripts/capture_bench.py timing --counts 20 50 150 --size 512 --out OUT
        procedural photos (make-scene --content textured --rig orbit, SIZE px) captured; seconds per phase, and the
        poses against the ones they were rendered with
    python scripts/capture_bench.py poses --scene DIR --out OUT
        capture DIR's photos (an LLFF scene: images_N/ and poses_bounds.npy) and compare with its shipped poses
        (median rotation error, centre error as a fraction of the cameras' spread)
    python scripts/capture_bench.py mixture --scene DIR --captured CAPTURE [CAPTURE ...] --recipe RECIPE --out OUT
        pretrain, build-moe, finetune (baseline, Top-2), eval on the shipped poses and on each capture's (e.g. one
        per --camera-model): held-out PSNR and GFLOPs, and each capture's poses against the shipped ones
    python scripts/capture_bench.py phone --count 50 [--density 3] --out OUT
        phone-sized photos (1080 x 1920 JPEG, portrait, the textured procedural scene on a walk around it; --density:
        its dots that many times as dense, for as many keypoints as a real photo gives) captured with the defaults:
        the seconds from photos to a scene folder, and the poses against the rendered ones
    python scripts/capture_bench.py video --out OUT
        a video of a walk around the textured procedural scene (300 frames, 30 per second, 360 x 640, two frames of
        every three blurred as a hand-held phone blurs them) captured with the defaults: seconds per phase, how many
        of the frames kept are sharp ones, and their poses against the rendered ones
    python scripts/capture_bench.py unbounded --out OUT
        photos from inside a world (make-scene --rig unbounded --content textured: the objects speckled with dots on a
        checkered ground under a banded sky, cameras on a ring) captured, then the unbounded CPU recipe with
        data.format and data.scene left to auto on capture's scene and on the rendered cameras: the kind chosen,
        the poses, held-out PSNR of the baseline and Top-2
    python scripts/capture_bench.py matching --captured OUT/capture-50 --out OUT
        exhaustive against retrieval matching on one capture's features (seconds, verified pairs)

Each writes OUT/<what>.json with the figures, the machine's load averages (os.getloadavg) before and after, and the
commit; timings taken on a busy machine are marked for a rerun on a quiet one.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def cli(*args: str, threads: int | None = None) -> str:
    """Run the boostnerf CLI of this checkout (with `threads`: that many torch threads); -> its stdout (raises with
    its stderr on failure)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), **({} if threads is None else {"OMP_NUM_THREADS": str(threads)})}
    proc = subprocess.run([sys.executable, "-m", "boostnerf_cli", *args], capture_output=True, text=True, env=env)
    if proc.returncode:
        raise SystemExit(f"boostnerf {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return proc.stdout


def commit() -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def record(out: Path, name: str, data: dict, load_before: tuple) -> None:
    data = {"commit": commit(), "load_before": [round(v, 2) for v in load_before],
            "load_after": [round(v, 2) for v in os.getloadavg()], "cpus": os.cpu_count(), **data}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(data, indent=2))
    print(json.dumps(data, indent=2))


def timing(args) -> None:
    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import compare_scenes

    load = os.getloadavg()
    rows = []
    for n in args.counts:
        src = args.out / f"photos-{n}"
        if not src.exists():
            cli("make-scene", str(src), "--format", "colmap", "--content", "textured", "--rig", "orbit",
                "--size", str(args.size), "--train-views", str(n), "--test-views", "0")
        cap = args.out / f"capture-{n}"
        t = time.perf_counter()
        cli("capture", "--images", str(src / "images"), "--out", str(cap), "--force")
        wall = time.perf_counter() - t
        report = json.loads((cap / "capture.json").read_text())
        errors = compare_scenes(load_scene(cap, holdout_every=0), load_scene(src, holdout_every=0))
        rows.append({"images": n, "size": args.size, "wall_seconds": round(wall, 1), "seconds": report["seconds"],
                     "matching": report["matching"], "registered": report["registered"], "points": report["points"],
                     "mean_reprojection_error": report["mean_reprojection_error"], **errors})
        record(args.out, "timing", {"rows": rows}, load)  # after each count: a long run keeps what it measured


def poses(args) -> None:
    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import compare_scenes

    load = os.getloadavg()
    folder = sorted(p for p in args.scene.iterdir() if p.is_dir() and p.name.startswith("images"))[0]
    cap = args.out / "capture"
    t = time.perf_counter()
    cli("capture", "--images", str(folder), "--out", str(cap), *(["--force"] if args.force else []))
    wall = time.perf_counter() - t
    report = json.loads((cap / "capture.json").read_text())
    errors = compare_scenes(load_scene(cap, holdout_every=0), load_scene(args.scene, holdout_every=0))
    record(args.out, "poses", {"scene": args.scene.name, "images": folder.name, "wall_seconds": round(wall, 1),
                               "capture": report, **errors}, load)


def _phone_photos(out: Path, count: int, width: int, height: int, density: float = 1.0) -> dict[str, np.ndarray]:
    """`count` JPEG photos of `width` x `height` of the textured procedural scene on an orbit (one ray per pixel; its
    dots `density` times as many along each axis: more keypoints per photo, as a real scene gives), written once to
    out/images; -> the camera-to-world pose each was rendered with, by file stem."""
    import imageio.v3 as iio
    import torch

    from boostnerf_cli.scenes import procedural as proc

    objects = [{**o, "scales": [v * density for v in o["scales"]]} for o in proc.scene_objects(0, "textured")]
    train, _ = proc.orbit_poses(count, 0)
    focal = 0.5 * width / math.tan(0.5 * proc.CAMERA_ANGLE_X)
    k = torch.tensor([focal, focal, width / 2, height / 2])
    (out / "images").mkdir(parents=True, exist_ok=True)
    poses = {}
    for i, pose in enumerate(train):
        name = f"IMG_{i:04d}.jpg"
        poses[Path(name).stem] = pose
        if not (out / "images" / name).exists():
            iio.imwrite(out / "images" / f".{name}", _render(objects, pose, k, width, height), extension=".jpg",
                        quality=92)
            (out / "images" / f".{name}").rename(out / "images" / name)
    return poses


def phone(args) -> None:
    """Phone-sized photos to a scene folder with the defaults: the target is 50 such photos in 3 minutes."""
    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import pose_errors, scene_poses

    tag = f"{args.count}" + (f"-dots{args.density:g}" if args.density != 1 else "")
    src = args.out / f"phone-{tag}"
    reference = _phone_photos(src, args.count, args.width, args.height, args.density)
    load = os.getloadavg()
    cap = args.out / f"phone-capture-{tag}"
    t = time.perf_counter()
    cli("capture", "--images", str(src / "images"), "--out", str(cap), "--force")
    wall = time.perf_counter() - t
    report = json.loads((cap / "capture.json").read_text())
    errors = pose_errors(scene_poses(load_scene(cap, holdout_every=0)), reference)
    record(args.out, f"phone-{tag}", {"images": args.count, "width": args.width, "height": args.height,
                                      "density": args.density, "keypoints_per_photo": report["keypoints"] // args.count,
                                      "wall_seconds": round(wall, 1), "capture": report, **errors}, load)


def _walk_poses(count: int) -> np.ndarray:
    """A smooth walk once around the scene, as a phone video: the azimuth sweeps a full turn while the height rises
    and falls twice (elevation 25-40 degrees), each camera looking at the origin -> (count, 4, 4)."""
    from boostnerf_cli.scenes import procedural as proc

    az = 2 * math.pi * np.arange(count) / count
    el = np.radians(32.5 + 7.5 * np.sin(2 * az))
    pos = proc.RADIUS * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return np.stack([proc.look_at(p) for p in pos])


def _render(objects: list, pose: np.ndarray, k, width: int, height: int) -> np.ndarray:
    """One view of `objects` (one ray per pixel, white where none is hit) -> (height, width, 3) uint8."""
    import torch

    from boostnerf_cli.render.rays import image_rays
    from boostnerf_cli.scenes import procedural as proc

    o, d = (v.double() for v in image_rays(torch.from_numpy(pose).float(), k, height, width))
    rgb = torch.ones_like(o)
    hits = [proc.intersect(obj, o, d) for obj in objects]
    nearest = torch.stack([h[0] for h in hits]).argmin(dim=0)
    for j, (obj, (t, n, p)) in enumerate(zip(objects, hits)):
        m = (nearest == j) & torch.isfinite(t)
        rgb[m] = proc.shade(obj, n[m], p[m])
    return (rgb.reshape(height, width, 3).numpy() * 255 + 0.5).astype(np.uint8)


def video(args) -> None:
    """A hand-held video around the scene to a scene folder: the frames capture keeps, and their poses."""
    import imageio_ffmpeg
    import torch

    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes import procedural as proc
    from boostnerf_cli.scenes.alignment import pose_errors, scene_poses

    poses = _walk_poses(args.count)
    clip = args.out / "walk.mp4"
    if not clip.exists():
        objects = proc.scene_objects(0, "textured")
        focal = 0.5 * args.width / math.tan(0.5 * proc.CAMERA_ANGLE_X)
        k = torch.tensor([focal, focal, args.width / 2, args.height / 2])
        args.out.mkdir(parents=True, exist_ok=True)
        tmp = args.out / ".walk.mp4"
        writer = imageio_ffmpeg.write_frames(str(tmp), (args.width, args.height), fps=args.fps, quality=8,
                                             macro_block_size=8)
        writer.send(None)
        for i, pose in enumerate(poses):
            image = _render(objects, pose, k, args.width, args.height)
            if i % 3:  # two frames of three moved while the shutter was open: a smear of 9 px along the walk
                image = np.mean([np.roll(image, s, axis=1) for s in range(-4, 5)], axis=0).astype(np.uint8)
            writer.send(np.ascontiguousarray(image))
        writer.close()
        tmp.rename(clip)
    load = os.getloadavg()
    cap = args.out / "video-capture"
    t = time.perf_counter()
    cli("capture", "--video", str(clip), "--out", str(cap), "--force")
    wall = time.perf_counter() - t
    report = json.loads((cap / "capture.json").read_text())
    frame = {Path(name).stem: round(sec * args.fps) for name, sec in report["video_seconds"].items()}
    reference = {name: poses[i] for name, i in frame.items()}
    errors = pose_errors(scene_poses(load_scene(cap, holdout_every=0)), reference)
    sharp = sum(i % 3 == 0 for i in frame.values())
    record(args.out, "video", {"frames_in_video": args.count, "fps": args.fps, "width": args.width,
                               "height": args.height, "frames_kept": len(frame), "sharp_frames_kept": sharp,
                               "wall_seconds": round(wall, 1), "capture": report, **errors}, load)


def _chain(scene: Path, recipe: Path, ws: Path, threads: int | None = None) -> dict:
    """pretrain, build-moe, baseline, Top-2 and eval on the test split (finished stages are skipped) -> eval.json."""
    for step in (("pretrain", "--data", str(scene)), ("build-moe",), ("finetune", "--baseline"),
                 ("finetune", "--topk", "2")):
        cli(*step, "--workspace", str(ws), "--recipe", str(recipe), "--device", "cpu", threads=threads)
    cli("eval", "--workspace", str(ws), "--split", "test", "--report", "--device", "cpu", threads=threads)
    return json.loads((ws / "reports" / "eval.json").read_text())


def unbounded(args) -> None:
    """A capture of an unbounded world, photos to a mixture, with the scene's kind left to `auto`."""
    import yaml

    sys.path.insert(0, str(ROOT))
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import pose_errors, scene_poses

    load = os.getloadavg()
    src, cap = args.out / "unbounded-scene", args.out / "unbounded-capture"
    if not src.exists():
        cli("make-scene", str(src), "--format", "nerfstudio", "--rig", "unbounded", "--content", "textured", "--size",
            str(args.size), "--train-views", str(args.count), "--test-views", "0")
    t = time.perf_counter()
    if not cap.exists():
        cli("capture", "--images", str(src / "images"), "--out", str(cap))
    wall = time.perf_counter() - t
    estimated, rendered = (scene_poses(load_scene(f, holdout_every=0)) for f in (cap, src))
    errors = pose_errors(estimated, {Path(name).name: pose for name, pose in rendered.items()})  # images/frame_00001
    rec = yaml.safe_load((ROOT / "recipes" / "unbounded-dvgo-cpu.yaml").read_text())
    rec["data"] = {k: v for k, v in rec["data"].items() if k not in ("format", "scene")}  # both left to auto
    recipe = args.out / "unbounded-auto.yaml"
    recipe.write_text(yaml.safe_dump(rec))
    results = {}
    for name, scene in (("rendered", src), ("captured", cap)):
        ws = args.out / f"ws-unbounded-{name}"
        report = _chain(scene, recipe, ws)
        described = json.loads((ws / "manifest.json").read_text())["scene"]
        kind = "unbounded" if described.get("contraction") else "forward" if described.get("ndc") else "bounded"
        results[name] = {"kind": kind, "psnr": {m["name"]: m.get("psnr") for m in report.get("models", [])}}
    record(args.out, "unbounded", {"photos": args.count, "size": args.size, "capture_seconds": round(wall, 1),
                                   "capture": json.loads((cap / "capture.json").read_text()), **errors,
                                   "chains": results}, load)


def mixture(args) -> None:
    """The chain on the shipped poses and on each capture's, two chains at a time with one thread each (the
    machine's two cores); the captures' poses against the shipped ones beside their scores."""
    sys.path.insert(0, str(ROOT))
    from concurrent.futures import ThreadPoolExecutor

    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.alignment import compare_scenes

    load = os.getloadavg()
    scenes = {"shipped": args.scene, **{f"captured:{c.name}": c for c in args.captured}}
    threads = 1 if args.parallel > 1 else None

    def chain(name: str) -> dict:
        return _chain(scenes[name], args.recipe, args.out / f"ws-{name.replace(':', '-')}", threads=threads)

    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        reports = dict(zip(scenes, pool.map(chain, scenes)))
    shipped = load_scene(args.scene, holdout_every=0)
    results = {}
    for name, report in reports.items():
        models = {m["name"]: {k: m.get(k) for k in ("psnr", "ssim", "w0", "gflops_per_image")} for m in
                  report.get("models", [])}
        results[name] = {"models": models}
        if name != "shipped":
            results[name]["poses"] = compare_scenes(load_scene(scenes[name], holdout_every=0), shipped)
            facts = json.loads((scenes[name] / "capture.json").read_text())
            results[name]["capture"] = {k: facts.get(k) for k in ("camera_models", "focal_aspect", "registered",
                                                                   "mean_reprojection_error")}
    record(args.out, "mixture", {"recipe": str(args.recipe), "scene": args.scene.name, "results": results}, load)


def matching(args) -> None:
    """Seconds of each matching kind on one finished capture's features (its database copied): where exhaustive
    matching stops being the faster (`capture.EXHAUSTIVE_MAX`)."""
    import shutil
    import tempfile

    sys.path.insert(0, str(ROOT))
    import pycolmap

    from boostnerf_cli.stages import capture

    pycolmap.logging.minloglevel = 2
    load = os.getloadavg()
    names = [p.name for p in capture.photo_files(args.captured / "images")]
    rows = []
    for kind in ("exhaustive", "retrieval"):
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            shutil.copy(args.captured / "database.db", work / "database.db")
            t = time.perf_counter()
            verified = capture._match(pycolmap, work, names, kind, 0)
            rows.append({"kind": kind, "images": len(names), "seconds": round(time.perf_counter() - t, 1),
                         "pairs": len(capture.pairs(len(names), "exhaustive", None)) if kind == "exhaustive" else None,
                         "verified_pairs": verified})
    record(args.out, f"matching-{len(names)}", {"rows": rows}, load)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    t = sub.add_parser("timing")
    t.add_argument("--counts", type=int, nargs="+", default=[20, 50, 150])
    t.add_argument("--size", type=int, default=512)
    t.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("poses")
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true")
    m = sub.add_parser("mixture")
    m.add_argument("--scene", type=Path, required=True)
    m.add_argument("--captured", type=Path, nargs="+", required=True, help="one or more capture folders")
    m.add_argument("--parallel", type=int, default=2, help="chains run at once, one thread each (1: one at a time)")
    m.add_argument("--recipe", type=Path, required=True)
    m.add_argument("--out", type=Path, required=True)
    f = sub.add_parser("phone")
    f.add_argument("--count", type=int, default=50)
    f.add_argument("--width", type=int, default=1080)
    f.add_argument("--height", type=int, default=1920)
    f.add_argument("--density", type=float, default=1.0, help="the dots this many times as dense along each axis")
    f.add_argument("--out", type=Path, required=True)
    v = sub.add_parser("video")
    v.add_argument("--count", type=int, default=300)
    v.add_argument("--fps", type=int, default=30)
    v.add_argument("--width", type=int, default=360)
    v.add_argument("--height", type=int, default=640)
    v.add_argument("--out", type=Path, required=True)
    u = sub.add_parser("unbounded")
    u.add_argument("--count", type=int, default=48)
    u.add_argument("--size", type=int, default=384)
    u.add_argument("--out", type=Path, required=True)
    k = sub.add_parser("matching")
    k.add_argument("--captured", type=Path, required=True)
    k.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    {"timing": timing, "poses": poses, "mixture": mixture, "matching": matching,
     "phone": phone, "video": video, "unbounded": unbounded}[args.what](args)


if __name__ == "__main__":
    main()
