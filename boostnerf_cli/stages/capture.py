"""`boostnerf capture`: photos or a video in, a COLMAP scene folder out (`sparse/0` + `images/`, `images_2/`, ...),
which `pretrain --data` reads directly (scenes/colmap.py).

Phases, each recorded in the work folder's `state.json` once finished, so that a second run reuses them (`--force`
redoes them all):
1. images: the photos checked (readable, one size, at least 3) and copied, or a video's frames chosen (`frames`:
   N evenly spaced windows, the sharpest frame of each by scikit-image's blur measure) and written as JPEG;
2. features: COLMAP's SIFT (pycolmap), on images scaled to `feature_size` at most;
3. matching: pairs chosen here (`pairs`), then matched and verified by pycolmap: a video's frames with their
   `SEQUENTIAL_OVERLAP` neighbours plus loop-closure pairs found by retrieval; photos exhaustively up to
   `EXHAUSTIVE_MAX` images, past it each with its `RETRIEVAL_NEIGHBOURS` most similar ones (retrieval, below) and its
   neighbours in file order, so the pairs grow linearly with the photos, not quadratically;
4. mapping: COLMAP's incremental mapper; the largest model is kept;
5. downscaling: `images_2/`, `images_4/`, `images_8/` (area), so a CPU run does not decode full-size photos.

Retrieval needs no downloaded vocabulary: a visual vocabulary of `VOCABULARY_WORDS` words is learned from the
capture's own SIFT descriptors (k-means), each image becomes a tf-idf histogram of its words, and the most similar
histograms give the pairs. COLMAP's vocabulary-tree matching would need a vocabulary file to be downloaded.

The inputs are known by their content (`fingerprint`: each file's name and size, and a digest of their bytes): a
finished capture of the same inputs and settings is kept, and a photo replaced under the same name is another input.

Everything is written into a hidden work folder beside the output (`.NAME.capture`) and renamed to the output only when
every phase is done: a capture stopped half way leaves nothing that `pretrain` would take for a scene.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from boostnerf_cli.cameras import rendered_models
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes.frames import IMAGE_SUFFIXES, one_line
from boostnerf_cli.train import Progress
from boostnerf_cli.workspace import read_json, write_json

log = logging.getLogger(__name__).info

EXHAUSTIVE_MAX = 30  # photos matched exhaustively up to this many (docs/capture.md: retrieval is faster past it)
RETRIEVAL_NEIGHBOURS = 20  # past it, each photo is matched with this many most similar ones
SEQUENTIAL_OVERLAP = 10  # a video frame is matched with this many next frames
LOOP_NEIGHBOURS = 5  # and with this many most similar frames farther away (loop closure)
VOCABULARY_WORDS = 256
VIDEO_FRAMES = 100  # a 30-60 s phone video: one frame every 0.3-0.6 s
CAMERA_MODELS = rendered_models()  # the models capture estimates: those boostnerf renders (cameras.MODELS)
PHASES = ("images", "features", "matching", "mapping", "downscale")
INSTALL = 'pip install -e ".[capture]"  (or: pip install pycolmap)'


@dataclass(frozen=True)
class CaptureOptions:
    camera_model: str = "OPENCV"
    per_image_cameras: bool = False
    feature_size: int = 1024  # SIFT on images whose longer side is at most this many pixels
    frames: int = VIDEO_FRAMES  # a video's frames to keep
    matching: str = "auto"  # auto, exhaustive, sequential or retrieval
    seed: int = 0


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise BoostNerfError(f"boostnerf capture needs pycolmap, which is not installed: {INSTALL}") from None
    return pycolmap


class _Work:
    """The work folder and its record of finished phases."""

    def __init__(self, root: Path):
        self.root = root
        self.state_path = root / "state.json"
        self.state = read_json(self.state_path, "capture state") if self.state_path.is_file() else {}

    def done(self, phase: str, signature: dict) -> bool:
        return self.state.get(phase, {}).get("signature") == signature

    def finish(self, phase: str, signature: dict, seconds: float, **facts) -> None:
        self.state[phase] = {"signature": signature, "seconds": seconds, **facts}
        write_json(self.state_path, self.state)

    def forget_from(self, phase: str) -> None:
        for later in PHASES[PHASES.index(phase):]:
            self.state.pop(later, None)
        write_json(self.state_path, self.state)


# ----------------------------------------------------------------------------- images


def photo_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise BoostNerfError(f"--images {folder} is not a folder: give the folder that holds the photos")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                   and not p.name.startswith("."))
    if not files:
        raise BoostNerfError(f"{folder} holds no photos (.jpg, .jpeg or .png): give the folder that holds them")
    if len(files) < 3:
        raise BoostNerfError(f"{folder} holds {len(files)} photo(s): a capture needs at least 3 (20 or more, each "
                             "spot of the subject in 3 or more of them, is better)")
    return files


def check_photos(files: list[Path]) -> tuple[int, int]:
    """Every photo readable to its last pixel and of one size -> (width, height); one line for the first that is
    not (checked before features, matching and mapping, not found at the downscale after them)."""
    from PIL import Image

    size = None
    for f in files:
        try:
            with Image.open(f) as im:
                im.verify()
            with Image.open(f) as im:  # decoded whole: a file cut short passes verify() and fails only when read
                im.load()
                this = im.size
        except Exception as err:  # PIL raises many types for a damaged file
            raise BoostNerfError(f"cannot read photo {f} ({one_line(err)}): remove or replace it") from None
        if size is None:
            size = this
        elif this != size:
            raise BoostNerfError(f"photo {f.name} is {this[0]} x {this[1]} but {files[0].name} is {size[0]} x "
                                 f"{size[1]}: one capture needs photos of one size (one camera, one orientation); "
                                 "turn or remove the odd ones")
    return size


def _copy_photos(files: list[Path], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for f in files:
        shutil.copy2(f, out / f.name)


def video_frames(path: Path, count: int, out: Path) -> dict[str, float]:
    """Write `count` frames of the video at `path` into `out` (frame_0001.jpg, ...): the video's frames cut into
    `count` windows of equal length, and of each the sharpest (least `skimage.measure.blur_effect`, on a small grey
    copy); -> the second of the video each file written is (its frame's number over the frames per second), by
    name."""
    import imageio.v3 as iio
    import imageio_ffmpeg
    from skimage.measure import blur_effect

    def frames(params=None):
        try:
            gen = imageio_ffmpeg.read_frames(str(path), output_params=params)
            meta = next(gen)
        except (RuntimeError, OSError, StopIteration) as err:
            raise BoostNerfError(f"cannot read the video {path} ({one_line(err)}): an unknown codec or not a video; "
                                 "convert it to H.264 MP4 (ffmpeg -i IN -c:v libx264 OUT.mp4)") from None
        return meta, gen

    meta, gen = frames(["-vf", "scale=320:-2"])
    width, height = meta["size"]
    blur = []
    try:
        for raw in gen:
            grey = np.frombuffer(raw, np.uint8).reshape(height, width, 3).mean(-1)
            blur.append(blur_effect(grey))
    except RuntimeError as err:
        raise BoostNerfError(f"cannot decode the video {path} ({one_line(err)}): convert it to H.264 MP4") from None
    if len(blur) < 3:
        raise BoostNerfError(f"the video {path} has {len(blur)} frame(s): a capture needs at least 3; record a "
                             "longer video around the subject")
    count = min(count, len(blur))
    edges = np.linspace(0, len(blur), count + 1).round().astype(int)
    keep = {int(a + np.argmin(blur[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a}
    meta, gen = frames()
    width, height = meta["size"]
    fps = float(meta.get("fps") or 0) or 1.0  # a stream that states none: frame numbers as they are
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for i, raw in enumerate(gen):
        if i in keep:
            name = f"frame_{len(written) + 1:04d}.jpg"
            iio.imwrite(out / name, np.frombuffer(raw, np.uint8).reshape(height, width, 3), quality=95)
            written[name] = round(i / fps, 4)
    return written


# ----------------------------------------------------------------------------- pairs


def _vocabulary_vectors(descriptors: list[np.ndarray], words: int, seed: int) -> np.ndarray:
    """tf-idf histograms (N, words), unit length, of each image's SIFT descriptors over a vocabulary learned by
    k-means from a sample of them (retrieval without a downloaded vocabulary)."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    pool = torch.cat([torch.from_numpy(d[:: max(1, len(d) // 200)].astype(np.float32)) for d in descriptors if len(d)])
    if len(pool) < words:
        words = max(1, len(pool))
    centres = pool[torch.randperm(len(pool), generator=gen)[:words]].clone()
    for _ in range(10):
        assign = torch.cdist(pool, centres).argmin(1)
        sums = torch.zeros_like(centres).index_add_(0, assign, pool)
        counts = torch.bincount(assign, minlength=words).float()
        centres = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], centres)
    hist = torch.zeros(len(descriptors), words)
    for i, d in enumerate(descriptors):
        if len(d):
            w = torch.cdist(torch.from_numpy(d.astype(np.float32)), centres).argmin(1)
            hist[i] = torch.bincount(w, minlength=words).float()
    idf = torch.log(len(descriptors) / (1 + (hist > 0).sum(0).float()))
    vec = hist / hist.sum(1, keepdim=True).clamp_min(1) * idf
    return torch.nn.functional.normalize(vec, dim=1).numpy()


def similar(vectors: np.ndarray, k: int, away: int = 0) -> list[tuple[int, int]]:
    """For each image its `k` most similar images (cosine of `vectors`) at least `away` + 1 places from it."""
    sim = vectors @ vectors.T
    n = len(vectors)
    index = np.arange(n)
    sim[np.abs(index[:, None] - index[None, :]) <= away] = -np.inf
    pairs = []
    for i in range(n):
        for j in np.argsort(-sim[i])[:k]:
            if np.isfinite(sim[i, j]):
                pairs.append((i, int(j)))
    return pairs


def pairs(n: int, kind: str, vectors: np.ndarray | None) -> list[tuple[int, int]]:
    """The image pairs to match (indices in name order, i < j, no repeats) for `kind`: exhaustive, sequential (a
    video: `SEQUENTIAL_OVERLAP` next frames, and `LOOP_NEIGHBOURS` similar frames farther away) or retrieval (photos:
    `RETRIEVAL_NEIGHBOURS` most similar, and the 5 next in file order)."""
    if kind == "exhaustive":
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    window = SEQUENTIAL_OVERLAP if kind == "sequential" else 5
    found = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + window + 1))}
    if vectors is not None:
        k, away = (LOOP_NEIGHBOURS, SEQUENTIAL_OVERLAP) if kind == "sequential" else (RETRIEVAL_NEIGHBOURS, 0)
        found |= {(min(i, j), max(i, j)) for i, j in similar(vectors, k, away)}
    return sorted(found)


def matching_kind(options: CaptureOptions, video: bool, n: int) -> str:
    if options.matching != "auto":
        return options.matching
    if video:
        return "sequential"
    return "exhaustive" if n <= EXHAUSTIVE_MAX else "retrieval"


# ----------------------------------------------------------------------------- phases


def _bar(title: str, total: int) -> Progress:
    return Progress(title, max(total, 1), 0, log_every=max(1, total // 4))


def _extract(pycolmap, work: Path, names: list[str], options: CaptureOptions) -> int:
    """SIFT of every image into work/database.db, in chunks (a bar with counts); -> keypoints in all."""
    db = work / "database.db"
    db.unlink(missing_ok=True)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = options.feature_size
    # one image at a time: the database numbers images as their features are written, and with more threads that
    # order (so the mapper's first pair, so every pose) follows the threads' timing (docs/capture.md, "The same
    # photos, the same scene")
    extraction.num_threads = 1
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    mode = pycolmap.CameraMode.PER_IMAGE if options.per_image_cameras else pycolmap.CameraMode.SINGLE
    bar = _bar("features", len(names))
    chunk = 8
    for start in range(0, len(names), chunk):
        pycolmap.extract_features(db, work / "images", image_names=names[start:start + chunk], camera_mode=mode,
                                  reader_options=reader, extraction_options=extraction)
        if start == 0 and not options.per_image_cameras:
            reader.existing_camera_id = 1  # one shared camera: the next chunks' images take the first one's
        bar.update(min(start + chunk, len(names)), {"images": min(start + chunk, len(names))})
    bar.close()
    with pycolmap.Database.open(db) as d:
        return int(d.num_keypoints())


def _match(pycolmap, work: Path, names: list[str], kind: str, seed: int) -> int:
    """Match the pairs `pairs` chooses, in chunks (a bar with counts); -> verified pairs."""
    db = work / "database.db"
    with pycolmap.Database.open(db) as d:
        d.clear_matches()
        d.clear_two_view_geometries()
        by_name = {im.name: im.image_id for im in d.read_all_images()}
        vectors = None
        if kind != "exhaustive":
            vectors = _vocabulary_vectors([d.read_descriptors(by_name[n]).data for n in names], VOCABULARY_WORDS, seed)
    todo = pairs(len(names), kind, vectors)
    bar = _bar(f"matching ({kind})", len(todo))
    chunk = 200
    pairing = pycolmap.ImportedPairingOptions()
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed  # COLMAP's default (-1) draws each pair's RANSAC samples anew every run
    for start in range(0, len(todo), chunk):
        listing = work / "pairs.txt"
        listing.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in todo[start:start + chunk]))
        pairing.match_list_path = str(listing)
        pycolmap.match_image_pairs(db, pairing_options=pairing, verification_options=verification)
        bar.update(min(start + chunk, len(todo)), {"pairs": min(start + chunk, len(todo))})
    bar.close()
    with pycolmap.Database.open(db) as d:
        return int(d.num_verified_image_pairs())


def _adjust_all(pycolmap, model) -> None:
    """One bundle adjustment of every camera, point and lens coefficient of `model`, in the steps
    pycolmap.bundle_adjustment takes (so, on the same threads, to the same numbers) but without its controller,
    which turns COLMAP's log back on (minloglevel 0) and prints its heading and timer among the bars."""
    pycolmap.ObservationManager(model).filter_observations_with_negative_depth()
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in model.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_extra_params = True
    options.print_summary = False
    options.ceres.solver_options.num_threads = 1  # with more, sums in an order that varies: other last bits
    pycolmap.create_default_bundle_adjuster(options, config, model).solve()
    model.update_point_3d_errors()


def _map(pycolmap, work: Path, given: int, seed: int) -> dict:
    """Incremental mapping; the largest model written to work/sparse/0; -> its facts."""
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.num_threads = 1  # with more, the mapper draws from worker threads whose random state depends on what
    # ran on them before (the matching): the same database would place the cameras otherwise
    # the lens's coefficients are held (at 0) while the cameras are placed, and refined in one bundle adjustment at
    # the end: refined from the first pair on, a lens of four coefficients can fit two views' noise so far that no
    # third photo registers (docs/capture.md, "Why the lens is held during mapping")
    options.ba_refine_extra_params = False
    bar = _bar("mapping", given)
    registered = [0]

    def next_image():
        registered[0] += 1
        bar.update(min(registered[0], given), {"registered": registered[0]})

    out = work / "mapping"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    models = pycolmap.incremental_mapping(work / "database.db", work / "images", out, options,
                                          next_image_callback=next_image)
    bar.close()
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    n = 0 if best is None else best.num_reg_images()
    check_registered(n, given, len(models))
    _adjust_all(pycolmap, best)
    target = work / "sparse" / "0"
    shutil.rmtree(work / "sparse", ignore_errors=True)
    target.mkdir(parents=True)
    best.write_binary(str(target))
    aspect = max(abs(c.focal_length_x / c.focal_length_y - 1) for c in best.cameras.values())
    return {"registered": n, "given": given, "models": len(models), "points": best.num_points3D(),
            "mean_reprojection_error": best.compute_mean_reprojection_error(),
            "camera_models": sorted({c.model.name for c in best.cameras.values()}), "focal_aspect": round(aspect, 5)}


def check_registered(registered: int, given: int, models: int) -> None:
    """Refuse a reconstruction whose largest model holds fewer than half of the images, in one line that says how
    many and what to do."""
    if registered == 0:
        raise BoostNerfError(f"no camera could be placed: the {given} images share too few features; take photos "
                             "with more overlap (each spot of the subject in 3 or more, neighbours sharing about "
                             "two thirds of the view) and more texture, or remove unrelated ones")
    if registered < given / 2:
        raise BoostNerfError(f"only {registered} of the {given} images could be placed in one model ({models} "
                             "separate models): the photos overlap too little; take more photos between the views "
                             "(neighbours sharing about two thirds of the view) or remove the unrelated ones, then "
                             "run again")


def _downscale(work: Path, names: list[str]) -> list[str]:
    """images_2/, images_4/, images_8/ (area-averaged, as long as the longer side stays 200 px or more)."""
    from PIL import Image

    with Image.open(work / "images" / names[0]) as im:
        longest = max(im.size)
    folders = []
    for factor in (2, 4, 8):
        if longest // factor < 200 and factor > 2:
            break
        out = work / f"images_{factor}"
        out.mkdir(exist_ok=True)
        for name in names:
            with Image.open(work / "images" / name) as im:
                small = im.convert("RGB").reduce(factor)
                small.save(out / name, **({"quality": 95} if name.lower().endswith((".jpg", ".jpeg")) else {}))
        folders.append(out.name)
    return folders


# ----------------------------------------------------------------------------- the command


def fingerprint(files: list[Path]) -> dict:
    """What a capture is made from, by content: each file's name and size, and one digest of their bytes in that
    order. A photo replaced under the same name, even of the same size and with its old modification time, gives
    another digest."""
    digest = hashlib.blake2b(digest_size=16)
    for f in files:
        digest.update(f"{f.name}|{f.stat().st_size}|".encode())
        with open(f, "rb") as stream:
            while block := stream.read(1 << 20):
                digest.update(block)
    return {"files": [[f.name, f.stat().st_size] for f in files], "digest": digest.hexdigest()}


def _inputs(images: Path | None, video: Path | None) -> dict:
    """The command's inputs as its report records them: where they are and their content (`fingerprint`)."""
    if (images is None) == (video is None):
        raise BoostNerfError("give either --images DIR (photos) or --video FILE, one of the two")
    if video is not None and not video.is_file():
        raise BoostNerfError(f"--video {video} is not a file: give the video's path")
    files = photo_files(images) if images is not None else [video]
    return {"images": str(images.resolve()) if images else None, "video": str(video.resolve()) if video else None,
            **fingerprint(files)}


def _work_folder(out: Path) -> Path:
    return out.parent / f".{out.name}.capture"


def run(images: Path | None, video: Path | None, out: Path, options: CaptureOptions, force: bool) -> dict:
    """Capture into `out` (see the module docstring) -> the report (also written to out/capture.json)."""
    inputs = _inputs(images, video)
    out = Path(out)
    report_path = out / "capture.json"
    if out.exists() and not report_path.is_file() and any(out.iterdir()):
        raise BoostNerfError(f"{out} already holds files that are no capture of boostnerf: choose a new folder")
    if report_path.is_file() and not force:
        report = read_json(report_path, "capture report")
        if report.get("inputs") == inputs and report.get("options") == asdict(options):
            log(f"{out} is already captured from these inputs with these settings (add --force to redo it)")
            return report
        raise BoostNerfError(f"{out} was captured from other inputs or settings: add --force to capture it again, or "
                             "choose a new folder")
    pycolmap = _pycolmap()
    # COLMAP's own log: fatal errors only. The bars say how it goes, and what goes wrong is boostnerf's one line (its
    # "Failed to create any sparse model" came before "no camera could be placed")
    pycolmap.logging.minloglevel = 3
    work = _work_folder(out)
    if force:
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    state = _Work(work)
    facts = _phases(pycolmap, state, inputs, images, video, options)
    report = {"inputs": inputs, "options": asdict(options), **facts,
              "seconds": {p: round(state.state[p]["seconds"], 2) for p in PHASES}}
    write_json(work / "capture.json", report)
    if out.exists():  # --force over a finished capture: the new one replaces it whole
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    work.rename(out)
    return report


def _phases(pycolmap, state: _Work, inputs: dict, images: Path | None, video: Path | None,
            options: CaptureOptions) -> dict:
    work = state.root
    sig = {"inputs": inputs, "frames": options.frames if video else None}
    if not state.done("images", sig):
        state.forget_from("images")
        t = time.perf_counter()
        shutil.rmtree(work / "images", ignore_errors=True)
        kept = {}
        if images is not None:
            files = photo_files(images)
            check_photos(files)
            _copy_photos(files, work / "images")
        else:
            kept = {"video_seconds": video_frames(video, options.frames, work / "images")}
            check_photos(photo_files(work / "images"))
        state.finish("images", sig, time.perf_counter() - t, **kept)
    names = [p.name for p in photo_files(work / "images")]
    log(f"images: {len(names)} {'frames of ' + str(video) if video else 'photos'}")
    steps = (
        ("features", {**sig, "camera_model": options.camera_model, "per_image": options.per_image_cameras,
                      "feature_size": options.feature_size},
         lambda: {"keypoints": _extract(pycolmap, work, names, options)}),
        ("matching", {"kind": matching_kind(options, video is not None, len(names)), "seed": options.seed},
         lambda: {"verified_pairs": _match(pycolmap, work, names, matching_kind(options, video is not None,
                                                                                 len(names)), options.seed)}),
        ("mapping", {"seed": options.seed}, lambda: _map(pycolmap, work, len(names), options.seed)),
        ("downscale", {}, lambda: {"folders": _downscale(work, names)}),
    )
    facts: dict = {"matching": steps[1][1]["kind"],  # and for a video, where in it each frame kept is
                   **{k: v for k, v in state.state["images"].items() if k not in ("signature", "seconds")}}
    for phase, signature, do in steps:
        if state.done(phase, signature):
            log(f"{phase}: done before, reused (--force redoes it)")
        else:
            state.forget_from(phase)
            t = time.perf_counter()
            result = do()
            state.finish(phase, signature, time.perf_counter() - t, **result)
        facts.update({k: v for k, v in state.state[phase].items() if k not in ("signature", "seconds")})
    return facts
