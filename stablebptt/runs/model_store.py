"""The model a run keeps, so that it resumes and renders after its MJCF file moved.

A single run keeps ``model.xml`` (the file as given) and ``model.mjb.gz`` (the
model compiled, includes and meshes inside, compressed: a skybox texture alone
can make it megabytes). A grid's cells keep ``model.xml`` and ``model.json``,
which names one compressed copy per model in the grid root's ``models/``.
``model_to_reopen`` chooses between the original file and the kept copy.
"""
from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import numpy as np

from stablebptt.errors import InputError, StorageError
from stablebptt.storage import atomic_write, file_sha256, read_json, write_json

MODEL_COPY_FILE = "model.xml"  # a copy of the MJCF file a run trained on
MODEL_PACKED_FILE = "model.mjb.gz"  # the same model compiled, with everything it includes, gzip-compressed
MODEL_LINK_FILE = "model.json"  # in a grid's cell: where the one compressed copy its grid keeps lies
MODEL_BINARY_FILE = "model.mjb"  # the compiled copy as earlier versions kept it (uncompressed); still read
SHARED_MODELS = "models"  # a grid root's folder of compressed models, each named by its content's SHA-256


def compiled_model(model_file: str | Path) -> bytes:
    """The MuJoCo binary (``.mjb``) of a model file: an MJCF compiled, includes and meshes inside;
    a compiled file (``.mjb``, or ``.mjb.gz`` as runs keep it) as it is."""
    import mujoco

    from stablebptt.physics import mujoco_log
    model_file = Path(model_file)
    if model_file.suffix in (".mjb", ".gz"):
        return _unpacked(model_file)
    with mujoco_log.collected():  # the task reported them when it loaded the file
        model = mujoco.MjModel.from_xml_path(str(model_file))
    binary = np.zeros(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, binary)
    return binary.tobytes()


def _unpacked(path: Path) -> bytes:
    """The bytes of a compiled model file, uncompressed if it is ``.gz``."""
    import gzip
    import zlib
    data = path.read_bytes()
    if path.suffix != ".gz":
        return data
    try:
        return gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as error:  # gzip.BadGzipFile is an OSError
        raise InputError(f"cannot load {path}: it is damaged ({error})") from None


def load_compiled_model(path: str | Path):
    """A ``mujoco.MjModel`` from a compiled model file: ``.mjb``, or ``.mjb.gz`` as runs keep it."""
    import mujoco
    path = Path(path)
    name = path.name.removesuffix(".gz")
    try:
        return mujoco.MjModel.from_binary_path(name, assets={name: _unpacked(path)})
    except ValueError as error:
        raise InputError(f"cannot load {path}: {' '.join(str(error).split())}") from None


def keep_model(run_dir: Path, model_file: str | Path) -> None:
    """Keep in ``run_dir`` what reopening its model needs after the file moved: the file as given
    (``model.xml``, an MJCF's own text) and the model compiled, includes and meshes inside, compressed
    (``model.mjb.gz``; a skybox texture alone can make it megabytes).

    A grid's cells share one compressed copy in the grid's root instead (``share_model``), each
    cell keeping ``model.json`` naming it (``link_model``); ``SharedModels`` compiles it once.
    """
    _copy_text(Path(run_dir), Path(model_file))
    atomic_write(Path(run_dir) / MODEL_PACKED_FILE, _pack(compiled_model(model_file)))


def share_model(root: Path, model_file: str | Path) -> Path:
    """The model compiled and compressed in a grid root, ``root/models/<SHA-256>.mjb.gz``: written
    when not there yet (atomically: one that exists is whole); returns its path."""
    binary = compiled_model(model_file)
    target = Path(root) / SHARED_MODELS / f"{hashlib.sha256(binary).hexdigest()}.mjb.gz"
    if not target.is_file():
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise StorageError(error.errno, f"cannot create {target.parent}: {error.strerror}") from None
        atomic_write(target, _pack(binary))
    return target


def link_model(run_dir: Path, model_file: str | Path, target: Path) -> None:
    """A grid cell's model: the file as given (``model.xml``) and ``model.json``, which names the grid's
    compiled copy ``target`` (``share_model``) relative to the cell, so a grid moved as a whole reopens."""
    run_dir = Path(run_dir)
    _copy_text(run_dir, Path(model_file))
    digest = Path(target).name.removesuffix(".mjb.gz")
    write_json(run_dir / MODEL_LINK_FILE, {"compiled": os.path.relpath(target, run_dir), "sha256": digest})


class SharedModels:
    """``share_model`` into one grid root, each model file compiled once however many cells keep it
    (cells are written from several threads)."""

    def __init__(self, root: Path):
        self.root, self._kept, self._lock = Path(root), {}, threading.Lock()

    def __call__(self, model_file: str | Path) -> Path:
        with self._lock:
            if str(model_file) not in self._kept:
                self._kept[str(model_file)] = share_model(self.root, model_file)
            return self._kept[str(model_file)]


def _copy_text(run_dir: Path, model_file: Path) -> None:
    """``model.xml``: an MJCF file's own text, as given (a compiled file has none to keep)."""
    if model_file.suffix not in (".mjb", ".gz"):
        atomic_write(run_dir / MODEL_COPY_FILE, model_file.read_bytes())


def _pack(binary: bytes) -> bytes:
    import gzip
    return gzip.compress(binary, compresslevel=6, mtime=0)  # no time stamp: the same model, the same bytes


def copy_model(run_dir: Path, model_file: str | Path) -> None:
    """``keep_model`` into the run folder alone (a single run)."""
    keep_model(run_dir, model_file)


def kept_model(run_dir: Path) -> Path | None:
    """The compiled copy of its model a run folder keeps (``keep_model``; an earlier version's
    ``model.mjb``), or None when it keeps none."""
    run_dir = Path(run_dir)
    for name in (MODEL_PACKED_FILE, MODEL_BINARY_FILE):
        if (run_dir / name).is_file():
            return run_dir / name
    link = run_dir / MODEL_LINK_FILE
    if not link.is_file():
        return None
    pointer = read_json(link)
    if not (isinstance(pointer, dict) and isinstance(pointer.get("compiled"), str)):
        raise InputError(f"{link} does not name a compiled model ('compiled': a path)")
    target = run_dir / pointer["compiled"]
    if not target.is_file():
        raise InputError(f"{link} names {target}, which does not exist: the grid's {SHARED_MODELS} folder was "
                         "moved or deleted; move the grid as a whole, or put the file back")
    return target


def model_to_reopen(run_dir: Path, record: dict) -> tuple[str | None, str]:
    """(the model file to rebuild a run's task from, a note for the user), or (None, "") for no model file.

    The file the run started from while it is unchanged; the run's compiled copy
    when that file is gone (moved, or another working directory). A changed file
    is refused: the run would train or show another system than it recorded.
    """
    resolved = record.get("resolved_task") or {}
    original = resolved.get("model_file")
    if not original:
        return None, ""
    original = Path(original)
    if original.is_file():
        if resolved.get("model_sha256") not in (None, file_sha256(original)):
            raise InputError(f"{original} changed since the run in {run_dir} started: restore it (the run's copy is "
                             f"{run_dir / MODEL_COPY_FILE}), or start a new run with the changed file")
        return str(original), ""
    copy = kept_model(run_dir)
    if copy is None:
        raise InputError(f"{original} does not exist any more and {run_dir} keeps no compiled copy of it "
                         f"({MODEL_PACKED_FILE}): put the file back")
    return str(copy), f"{original} is gone: using the run's own copy, {copy}"
