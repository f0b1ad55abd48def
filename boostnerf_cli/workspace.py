"""The on-disk contract of a workspace: paths, manifest, atomic writes, a writer lock.

WS/manifest.json                  scene, recipe, and what each stage produced from what
WS/experts/<model>-<res>.safetensors  expert weights (config as JSON in the metadata)
WS/experts/<model>-<res>.json     its training report
WS/experts/geometry.safetensors   the shared coarse geometry (box + occupancy) all experts start from
WS/moe/<name>.safetensors         mixtures (untrained `init`, finetuned `top1`, `top2`, `ens`), `baseline`
WS/moe/<name>-pruned.safetensors  a model with its unused grid rows dropped (`prune`; packed tables, below)
WS/checkpoints/<name>.pt          resumable training state, removed when the stage finishes
WS/renders/<model>/<split>/...    images, depth, per-expert views, gate maps
WS/reports/eval.json, count-params.json

Every file appears only when complete: it is written to a temporary name in the same folder, then
renamed over the target (atomic on POSIX), so a crash never leaves a half-written artifact and never
destroys the previous version. Every safetensors file carries a `digest` of its tensors; stages
record the digests of their inputs in the manifest and their outputs, and refuse stale inputs.
One process writes a workspace at a time (`Workspace.lock`). Every write and removal through this module is
counted (`writes`): what a command read before the count moved may be out of date (`lineage.Survey` reads again).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import math
import os
import re
import shutil
import socket
import tempfile
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, Iterator

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from boostnerf_cli.errors import BoostNerfError

FORMAT_VERSION = "2"


def is_temporary(path: Path) -> bool:
    """A temporary file of `atomic_path` (`.NAME.XXXX.tmp`, or `.NAME.XXXX.tmp.mp4` for a writer that needs the
    suffix: ffmpeg) or folder of `make_scene` (`.NAME.tmp`)."""
    name = path.name
    return name.startswith(".") and (name.endswith(".tmp") or ".tmp." in name)


# `atomic_path`'s temporary files: `.NAME.` + mkstemp's 8 random characters + `.tmp` (+ the target's suffix)
_TEMP_FILE = re.compile(r"\.(.+)\.[a-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?")
# The folders a workspace's writers write in (bench adds rows/ and variants/, each variant a workspace), the files
# they write in its root, and the embedded scene's folder while make_scene generates it (pretrain or bench without
# --data).
WRITTEN_FOLDERS = ("experts", "moe", "reports", "checkpoints", "cache", "renders", "camera_paths", "rows", "variants")
ROOT_FILES = ("manifest.json", "bench-config.json")
SCENE_TMP = ".scene.tmp"


def recorded_path(data: Path, root: Path) -> str:
    """How a workspace (or bench folder) `root` records its scene `data`: relative to it for a scene inside it (the
    generated default scene: it travels with a moved or copied folder), else absolute, through any symbolic link as
    given (so repointing the link relocates the scene)."""
    here, top = data.resolve(), root.resolve()
    return os.path.relpath(here, top) if here.is_relative_to(top) else os.path.abspath(data)


def stale_temporaries(root: Path) -> list[Path]:
    """What a writer killed mid-write can have left in workspace `root`, and nothing else: `atomic_path`'s
    temporary files of `ROOT_FILES` in `root` itself and of any file at any depth of `WRITTEN_FOLDERS` (not in a
    hidden folder, nor in a folder that holds its own `.lock`: another workspace, whose writer may be live), and the
    embedded scene being generated (`SCENE_TMP`). A user's files elsewhere in the folder (`-w .`, `-w ~/project`)
    are never touched."""
    found = [root / SCENE_TMP] if (root / SCENE_TMP).is_dir() and not (root / SCENE_TMP).is_symlink() else []
    for top in (root, *(root / name for name in WRITTEN_FOLDERS)):
        for folder, dirs, files in os.walk(top):  # symbolic links to folders are not followed
            if top == root:
                dirs.clear()  # root's own files only: its folders are the written ones above, or the user's
            else:
                dirs[:] = [d for d in dirs
                           if not d.startswith(".") and not os.path.lexists(os.path.join(folder, d, ".lock"))]
            matches = ((f, _TEMP_FILE.fullmatch(f)) for f in files)
            found += [Path(folder, f) for f, m in matches if m and (top != root or m.group(1) in ROOT_FILES)]
    return sorted(found)


_writes = 0  # files written or removed through this module by this process (`writes`)


def writes() -> int:
    """How many files this process has written (`atomic_path`) or removed (`remove`) so far: a reader that cached
    what it read compares the count to know whether to read again."""
    return _writes


def _wrote() -> None:
    global _writes
    _writes += 1


def remove(path: Path) -> None:
    """Remove file `path` (nothing when it is not there), counted as a write (`writes`)."""
    path.unlink(missing_ok=True)
    _wrote()


def check_writable(paths: list[Path]) -> None:
    """One line, before any work, when a file of `paths` cannot be written for what is in its way: a folder at its
    path, or a file where one of its folders goes."""
    for path in paths:
        path = Path(path)
        folder = path.parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        where = path if path.is_dir() else folder if not folder.is_dir() else None
        if where is not None:
            raise BoostNerfError(f"could not write {path}: a {'folder' if where.is_dir() else 'file'} is in the way "
                                 f"(at {where}): move it and rerun the same command")


@contextmanager
def atomic_path(target: Path, keep_suffix: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `target` (ending in `target`'s suffix too with `keep_suffix`, for writers
    that choose the format by it); rename it over `target` only if the block succeeds.

    The data is flushed to disk before the rename, so after a crash or power loss `target` is
    either the previous version or the complete new one. A failing write (disk full, read-only
    folder, ...) leaves the previous `target` untouched, removes the temporary file and becomes one
    `BoostNerfError` line.
    """
    tmp_path: Path | None = None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        suffix = ".tmp" + (target.suffix if keep_suffix else "")
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        yield tmp_path
        _fsync(tmp_path)
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, target)
        _wrote()
        _fsync_dir(target.parent)
    except OSError as e:
        reason = e.strerror or str(e) or type(e).__name__
        if e.errno in (errno.EEXIST, errno.ENOTDIR, errno.EISDIR):  # a file where a folder goes, or the reverse
            # the rename's error names the temporary file (gone by now) as its source: name what is in its way
            where = target if tmp_path is not None and e.filename == str(tmp_path) else e.filename or target
            advice = f"a file or folder is in the way (at {where}): move it and rerun the same command"
        else:
            advice = "free disk space or fix the folder's permissions and rerun the same command"
        raise BoostNerfError(f"could not write {target} ({reason}); the previous version, if any, is unchanged: "
                             + advice) from None
    finally:
        if tmp_path is not None and tmp_path.exists():
            tmp_path.unlink()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def json_ready(data: Any) -> Any:
    """`data` with every float that is not finite replaced by None. JSON has no inf or nan (RFC 8259); null is
    what JavaScript's JSON.stringify writes for them. A PSNR is inf where a render matches its image exactly."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: json_ready(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_ready(v) for v in data]
    return data


def write_json(path: Path, data: Any) -> None:
    """Strict JSON (a value that is not finite is written as null; see `json_ready`), written atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(json_ready(data), indent=2, sort_keys=False, allow_nan=False) + "\n")


def number(value: float | int | None, spec: str) -> str:
    """A report value for display: "-" for null (not available, or not finite when it was written)."""
    return "-" if value is None else format(value, spec)


def read_json(path: Path, what: str = "file", fix: str = "delete it and rerun the stage") -> dict:
    """A JSON object written by `write_json` (manifest, reports), or by hand (UTF-8, a byte-order mark allowed); one
    clear line for anything else, ending in `fix` where the contents are wrong (a file the user writes: "fix it")."""
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise BoostNerfError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise BoostNerfError(f"{what} {path} is a folder, not a file: move it away and rerun the stage") from None
    except OSError as e:
        raise BoostNerfError(f"cannot read {what} {path} ({e.strerror or type(e).__name__}): "
                             "fix its permissions") from None
    except (json.JSONDecodeError, UnicodeDecodeError, ValueError, RecursionError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise BoostNerfError(f"{what} {path} is not valid JSON ({reason}); {fix}") from None
    if not isinstance(data, dict):
        raise BoostNerfError(f"{what} {path} holds a JSON {type(data).__name__}, not an object: {fix}")
    return data


def save_tensors(path: Path, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """Safetensors file with `meta` stored as JSON under the metadata key `boostnerf`."""
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise BoostNerfError(f"refusing to write {path.name}: tensor {name!r} has non-finite values")
    clean = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    header = {"boostnerf": json.dumps({**meta, "format_version": FORMAT_VERSION, "digest": tensors_digest(clean)})}
    with atomic_path(path) as tmp:
        try:
            save_file(clean, str(tmp), metadata=header)
        except SafetensorError as e:  # e.g. "I/O error: No space left on device (os error 28)"
            raise OSError(str(e)) from None


class _RecordingFile:
    """A file wrapper that remembers the OSError of a failed write: torch.save reports a full disk
    only as an opaque RuntimeError ("enforce fail at inline_container.cc")."""

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, data):
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self):
        try:
            return self.f.flush()
        except OSError as e:
            self.error = e
            raise


def save_torch(path: Path, obj: Any) -> None:
    """`torch.save` atomically (used for training checkpoints); a failed write is one clear error."""
    with atomic_path(path) as tmp, open(tmp, "wb") as raw:
        out = _RecordingFile(raw)
        try:
            torch.save(obj, out)
        except RuntimeError:
            if out.error is not None:
                raise out.error from None
            raise


def tensors_digest(tensors: dict[str, torch.Tensor]) -> str:
    """Fingerprint of a set of named tensors (names, dtypes, shapes, bytes), stored in every file's
    metadata as `digest`: later stages record the digests of their inputs to detect stale ones."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(tensors):
        t = tensors[name].detach().contiguous().cpu()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        if t.numel():
            h.update(t.reshape(-1).view(torch.uint8).numpy())  # the bytes as they lie, not copied
    return h.hexdigest()


# What building a model from a file that loads but holds the wrong structure raises (a missing key, a
# value of the wrong type or range, a tensor of the wrong shape): callers turn it into one line (`malformed`).
MALFORMED = (KeyError, TypeError, ValueError, IndexError, AttributeError, ArithmeticError, RuntimeError)


def malformed(e: BaseException) -> str:
    """One line describing what was wrong in a file's contents, for the callers' error messages."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{type(e).__name__}: {text[:200]}" if text else type(e).__name__


def read_meta(path: Path) -> dict[str, Any]:
    """Only the metadata of a file written by `save_tensors` (cheap: reads the header)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = json.loads((f.metadata() or {})["boostnerf"])
    except (SafetensorError, OSError, KeyError, ValueError, TypeError) as e:
        raise BoostNerfError(
            f"checkpoint {path} is damaged or not a boostnerf file ({type(e).__name__}); "
            "delete it and rerun the stage that writes it"
        ) from None
    if not isinstance(meta, dict):
        raise BoostNerfError(f"checkpoint {path} is not a boostnerf file (its metadata is not an object); "
                             "delete it and rerun the stage that writes it")
    if meta.get("format_version") != FORMAT_VERSION:
        raise BoostNerfError(f"checkpoint {path} has file format {meta.get('format_version')!r}, and this boostnerf "
                             f"reads format {FORMAT_VERSION!r}: make it again with this one (delete it and rerun "
                             f"{_maker(path)}), or read it with the boostnerf that wrote it")
    return meta


def _maker(path: Path) -> str:
    """The command that writes a workspace's model file `path`, for messages."""
    if path.parent.name == "experts":
        return "`boostnerf pretrain`"
    if path.parent.name == "moe":
        return ("`boostnerf build-moe`" if path.stem == "init" else "`boostnerf prune`" if path.stem.endswith("-pruned")
                else "`boostnerf finetune`")
    return "the stage that writes it"


def load_tensors(path: Path, device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """-> (tensors, meta) on `device` from a file written by `save_tensors`; one clear error when it is damaged (it does
    not read, or its tensors are not those its digest was made of).

    Read on the CPU (where a pruned file's tables are rebuilt), then moved to `device` in one place."""
    if not path.exists():
        raise BoostNerfError(f"checkpoint {path} does not exist")
    meta = read_meta(path)
    try:
        tensors = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, KeyError, ValueError, json.JSONDecodeError) as e:
        raise BoostNerfError(
            f"checkpoint {path} is damaged or not a boostnerf file ({type(e).__name__}); "
            "delete it and rerun the stage that writes it"
        ) from None
    if "digest" in meta and tensors_digest(tensors) != meta["digest"]:  # 0.1 s for 74 MB, one thread
        raise BoostNerfError(f"checkpoint {path} is damaged: its tensors are not those written with it (their digest "
                             f"differs); delete it and rerun {_maker(path)}")
    if meta.get("packed"):
        tensors = _unpack_tensors(tensors, meta["packed"], path)
    return {k: v.to(device) for k, v in tensors.items()}, meta


# --- pruned (packed) tables ---------------------------------------------------------------------
# A pruned model stores some 2-D tables (V rows x C channels) as only their kept rows: `<name>@values`
# (n_kept, C) and `<name>@mask` (ceil(V / 8) bytes, one bit per row, numpy's big-endian bit order),
# listed in the metadata under "packed": {name: {"rows": V, "fill": [C values for dropped rows]}}.
# `load_tensors` rebuilds the dense table, so every loader reads a pruned file like any other.

def pack_rows(table: torch.Tensor, keep: torch.Tensor) -> dict[str, torch.Tensor]:
    """(V, C) table, (V,) bool -> {"values": (n_kept, C), "mask": packed bits (uint8)}."""
    import numpy as np

    keep = keep.detach().bool().cpu()
    bits = np.packbits(keep.numpy().astype(np.uint8))
    return {"values": table.detach().cpu()[keep].contiguous(), "mask": torch.from_numpy(bits)}


def _kept(mask: torch.Tensor, rows: int) -> torch.Tensor:
    """A packed table's `<name>@mask` bits -> (rows,) bool, True for the rows it stores."""
    import numpy as np

    return torch.from_numpy(np.unpackbits(mask.cpu().numpy(), count=rows).astype(bool))


def unpack_rows(values: torch.Tensor, mask: torch.Tensor, rows: int, fill: list[float]) -> torch.Tensor:
    """Inverse of `pack_rows`: the dense (rows, C) table, dropped rows set to `fill`."""
    keep = _kept(mask, rows)
    if int(keep.sum()) != values.shape[0] or len(fill) != values.shape[1]:
        raise ValueError("packed table does not match its mask")
    dense = torch.tensor(fill, dtype=values.dtype).expand(rows, values.shape[1]).clone()
    dense[keep] = values.cpu()
    return dense


def dropped_rows(path: Path, meta: dict[str, Any]) -> dict[str, torch.Tensor]:
    """{table name: (V,) bool, True where the pruned file `path` stores no row} ({} for a file that is not pruned)."""
    packed = meta.get("packed") or {}
    if not packed:
        return {}
    with safe_open(str(path), "pt") as f:
        return {name: ~_kept(f.get_tensor(f"{name}@mask"), int(info["rows"])) for name, info in packed.items()}


def _unpack_tensors(tensors: dict[str, torch.Tensor], packed: dict, path: Path) -> dict[str, torch.Tensor]:
    out = {k: v for k, v in tensors.items() if "@" not in k}
    for name, info in packed.items():
        try:
            dense = unpack_rows(tensors[f"{name}@values"], tensors[f"{name}@mask"], int(info["rows"]), info["fill"])
        except (KeyError, ValueError, TypeError):
            raise BoostNerfError(f"checkpoint {path} is damaged: its packed table {name!r} is incomplete; "
                                 "delete it and rerun `boostnerf prune`") from None
        out[name] = dense.to(tensors[f"{name}@values"].device)
    return out


def _remove_empty(root: Path, top: Path) -> None:
    """Remove the empty folders under `root`, then `root` and its parents up to `top` while they are empty."""
    with suppress(OSError):  # a folder that holds a file (or cannot be read) stays
        for sub in sorted((p for p in root.rglob("*") if p.is_dir() and not p.is_symlink()),
                          key=lambda p: len(p.parts), reverse=True):
            with suppress(OSError):
                sub.rmdir()
        for folder in (root, *root.parents):
            folder.rmdir()
            if folder == top:
                break


class Workspace:
    """Paths and manifest of one workspace directory."""

    def __init__(self, root: Path):
        self.root = Path(root)

    @contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive writer lock: an OS lock (`flock`) on WS/.lock, which holds the writer's host and pid.

        The kernel releases the lock when its process ends, however it ends (also `kill -9`), so a
        lock file left behind by a dead process is stale by construction and is taken over; a lock
        held by a live process is refused with one clear line.

        A workspace folder this call creates is removed again if the command leaves it empty (it failed
        before writing anything but the decoded scene's cache, which goes too): the empty folders under it, then it
        and the parents it made.
        """
        made = [p for p in (self.root, *self.root.parents) if not p.exists()]
        try:
            with self._locked():
                yield
        except BaseException:
            if made:  # failed in a workspace it made, having written nothing but the decoded scene: that goes too
                with suppress(OSError):
                    if [p for p in self.root.rglob("*") if not p.is_dir()] == [self.scene_cache]:
                        remove(self.scene_cache)
            raise
        finally:
            if made:
                _remove_empty(self.root, made[-1])

    @contextmanager
    def _locked(self) -> Iterator[None]:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise BoostNerfError(f"cannot create workspace {self.root} ({e.strerror or e})") from None
        path = self.root / ".lock"
        try:
            fd = self._acquire(path)
        except OSError as e:  # a read-only workspace, a .lock owned by another user or that is a folder, ...
            raise BoostNerfError(
                f"cannot take the writer lock {path} ({e.strerror or type(e).__name__}): "
                "fix the workspace folder's permissions (or remove that .lock) and rerun"
            ) from None
        try:
            yield
        finally:
            with suppress(OSError):  # a lock file left behind (read-only folder by now) is stale once released
                path.unlink(missing_ok=True)  # unlink while still holding the lock, then release it
            os.close(fd)

    @contextmanager
    def reading(self) -> Iterator[None]:
        """A reader's lock (`eval` without --report): a shared `flock` on WS/.lock, so several readers run at once,
        a writer is refused while they read, and a reader while a writer writes (it may be replacing what is read).
        A workspace a reader cannot lock, read-only (an archive, a read-only mount), has no writer either: it is
        read as it is. The last reader out removes the lock file; a reader writes nothing else."""
        path = self.root / ".lock"
        fd = None
        while True:
            try:
                fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
            except OSError as e:
                if e.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                    raise BoostNerfError(f"cannot open the workspace lock {path} ({e.strerror or type(e).__name__}): "
                                         "remove it if it is not a file, and rerun") from None
                try:  # a read-only workspace: its lock file, if a writer left one, can still be locked
                    fd = os.open(path, os.O_RDONLY)
                except OSError:
                    fd = None
                    break  # no lock file and none can be made: nobody can be writing it
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                locked = True
            except BlockingIOError:
                locked = False
            except OSError as e:  # a file system without locks (some network mounts), as the writer's lock says
                os.close(fd)
                raise BoostNerfError(f"cannot take the reader lock {path} ({e.strerror or type(e).__name__}): the "
                                     "workspace's file system must support flock; move the workspace to a local "
                                     "disk") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                same = False
            if same and locked:
                with suppress(OSError):  # a killed writer's "host pid" would be named to the next writer refused
                    os.ftruncate(fd, 0)
                break
            if same:  # held by a writer
                holder = os.read(fd, 200).decode(errors="replace").strip() if os.fstat(fd).st_size else ""
                os.close(fd)
                raise BoostNerfError(f"workspace {self.root} is being written by another boostnerf process "
                                     f"({holder or 'unknown'}): wait for it to finish, then rerun")
            os.close(fd)  # a lock file its holder unlinked while we opened it: open the new one
        try:
            yield
        finally:
            if fd is not None:
                with suppress(OSError):  # the last reader (no other holder) removes the file
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    path.unlink()
                os.close(fd)

    def _acquire(self, path: Path) -> int:
        """Lock `path` (-> its descriptor, which holds this host and pid) and clean up temporary files."""
        me = f"{socket.gethostname()} {os.getpid()}"
        while True:
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 200).decode(errors="replace").strip()
                os.close(fd)
                raise BoostNerfError(
                    f"workspace {self.root} is in use by another boostnerf process ({holder or 'reading it: eval'}): "
                    "wait for it to finish; a writer shares a workspace with no other command"
                ) from None
            except OSError:
                os.close(fd)
                raise
            try:
                same = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                same = False
            if same:  # not a file its previous holder unlinked just before we locked it
                break
            os.close(fd)
        try:
            os.ftruncate(fd, 0)
            os.write(fd, me.encode())
            # Temporary files of `atomic_path` left by a writer that was killed mid-write: never artifacts
            # (they were not renamed into place), and no other writer can be using them now.
            for tmp in stale_temporaries(self.root):
                if tmp.is_dir() and not tmp.is_symlink():  # a procedural scene being generated (`make_scene`)
                    shutil.rmtree(tmp, ignore_errors=True)
                else:
                    tmp.unlink(missing_ok=True)
        except OSError:
            with suppress(OSError):
                path.unlink(missing_ok=True)
            os.close(fd)
            raise
        return fd

    # paths
    @property
    def manifest_path(self) -> Path:
        return self.root / "manifest.json"

    @property
    def experts_dir(self) -> Path:
        return self.root / "experts"

    @property
    def moe_dir(self) -> Path:
        return self.root / "moe"

    @property
    def reports_dir(self) -> Path:
        return self.root / "reports"

    @property
    def checkpoints_dir(self) -> Path:
        return self.root / "checkpoints"

    def expert_path(self, name: str) -> Path:
        return self.experts_dir / f"{name}.safetensors"

    def expert_report_path(self, name: str) -> Path:
        return self.experts_dir / f"{name}.json"

    @property
    def geometry_path(self) -> Path:
        return self.experts_dir / "geometry.safetensors"

    @property
    def scene_cache(self) -> Path:
        """The workspace's scene as decoded, for the next stage to read back (scenes/cache.py)."""
        return self.root / "cache" / "scene.safetensors"

    def model_path(self, name: str) -> Path:
        return self.moe_dir / f"{name}.safetensors"

    def checkpoint_path(self, name: str) -> Path:
        return self.checkpoints_dir / f"{name}.pt"

    def renders_dir(self, model: str, split: str | None = None) -> Path:
        """WS/renders/MODEL/SPLIT (or WS/renders/MODEL): where `render` writes a model's pictures."""
        folder = self.root / "renders" / model
        return folder / split if split is not None else folder

    def own_file(self, path: Path) -> str | None:
        """What `path` is of the workspace's own files, which only the stages write: "manifest", or the folder of
        models, reports, checkpoints, cache or generated scene it lies in (links followed); None for any other path
        (renders/, camera_paths/, outside)."""
        path = Path(path).resolve()
        if path == self.manifest_path.resolve():
            return "manifest"
        for folder in ("experts", "moe", "reports", "checkpoints", "cache", "scene"):  # scene: the one generated here
            if path.is_relative_to((self.root / folder).resolve()):
                return f"{folder}/ folder"
        return None

    @property
    def camera_paths_dir(self) -> Path:
        """WS/camera_paths: the camera paths `view` saves (nerfstudio's layout) and `render --camera-path` renders."""
        return self.root / "camera_paths"

    # manifest
    def manifest(self) -> dict:
        """The workspace's manifest ({} when there is none); one line for one of another file format."""
        if not self.manifest_path.exists():
            return {}
        m = read_json(self.manifest_path, "workspace manifest")
        if m and m.get("format_version") != FORMAT_VERSION:
            raise BoostNerfError(f"workspace {self.root} has file format {m.get('format_version')!r}, and this "
                                 f"boostnerf reads format {FORMAT_VERSION!r}: make it again in a new workspace "
                                 "(`boostnerf pretrain --workspace NEW ...`), or use the boostnerf that made it")
        return m

    def require_manifest(self) -> dict:
        m = self.manifest()
        if not m:
            raise BoostNerfError(
                f"{self.root} is not a boostnerf workspace (no manifest.json): "
                f"run `boostnerf pretrain --workspace {self.root} ...` first"
            )
        return m

    def update_manifest(self, **sections: Any) -> dict:
        m = {"format_version": FORMAT_VERSION, **self.manifest()}
        for key, value in sections.items():
            if isinstance(value, dict) and isinstance(m.get(key), dict):
                m[key] = {**m[key], **value}
            else:
                m[key] = value
        write_json(self.manifest_path, m)
        return m

    def expert_files(self) -> list[str]:
        """Every expert with a weights file, finished or not (the geometry stage's file is not an expert), by name."""
        return sorted(p.stem for p in self.experts_dir.glob("*.safetensors") if p.stem != "geometry")

    def expert_names(self) -> list[str]:
        """Finished experts (weights and report), smallest first (by parameter count from their reports)."""
        names = [n for n in self.expert_files() if self.expert_report_path(n).exists()]
        params = {n: read_json(self.expert_report_path(n), "expert report").get("params", 0) for n in names}
        return sorted(names, key=lambda n: (params[n], n))

    def model_names(self) -> list[str]:
        return sorted(p.stem for p in self.moe_dir.glob("*.safetensors")) if self.moe_dir.exists() else []

    def all_model_names(self) -> list[str]:
        """Experts smallest first, then mixtures in the paper's order (moe/init, untrained, is no model to use)."""
        order = {"baseline": 0, "top1": 1, "top2": 2, "ens": 9}
        mixtures = sorted((n for n in self.model_names() if n != "init"), key=lambda n: (order.get(n, 5), n))
        return self.expert_names() + mixtures

    def model_file(self, name: str) -> Path:
        """Where model `name` lives: experts/NAME.safetensors, else moe/NAME.safetensors."""
        return self.expert_path(name) if self.expert_path(name).exists() else self.model_path(name)

    def report_path(self, name: str) -> Path:
        """The report of model `name`, written when it is finished: experts/NAME.json, else moe/NAME.json."""
        return self.expert_report_path(name) if self.expert_path(name).exists() else self.moe_dir / f"{name}.json"
