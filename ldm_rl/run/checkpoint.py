"""One checkpoint format for every recipe, exact resume, and runs that stop cleanly.

A checkpoint file (``checkpoint.pt`` in a run's folder) is::

    b"ldm_rl checkpoint\\n"                                   magic line
    {"format_version": 1, "meta_bytes": M, "state_bytes": S, "sha256": "<hex>"}\\n    header line (JSON)
    M bytes: meta, UTF-8 JSON (kind, preset, task, iteration, the resolved config, ...)
    S bytes: state, ``torch.save`` of plain containers of tensors and numbers

The SHA-256 covers meta and state: a flipped byte anywhere, a truncated or padded file, a file of
another kind or of a newer format version each give one :class:`CheckpointError` naming the file and
what is wrong, never a silently changed weight. The state loads with ``torch.load(weights_only=True)``,
so ``save_checkpoint`` turns numpy scalars into Python numbers and refuses what would not load that way
(numpy arrays, custom classes), naming where it is.

Pieces: :func:`save_checkpoint` (atomic: temporary + fsync + rename + fsync of the folder),
:func:`load_checkpoint` (verifies everything, checks ``expect``), :func:`read_checkpoint_meta`
(meta only, no torch), :func:`capture_rng_state` / :func:`restore_rng_state` (python, numpy, torch,
CUDA and named generators), :func:`clean_stale_temporaries` (what a kill during a save leaves behind). Stopping cleanly on a signal: :mod:`ldm_rl.run.signals`.

Nothing here imports torch at module import time.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import random
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

__all__ = [
    "FORMAT_VERSION",
    "CHECKPOINT_NAME",
    "CheckpointError",
    "Checkpoint",
    "save_checkpoint",
    "load_checkpoint",
    "read_checkpoint_meta",
    "check_meta",
    "capture_rng_state",
    "restore_rng_state",
    "clean_stale_temporaries",
]

FORMAT_VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"
MAGIC = b"ldm_rl checkpoint\n"
_MAX_HEADER = 4096
# tempfile's random names: 8 characters of [a-z0-9_]; outputs.atomic_path and save_checkpoint both
# name their temporaries ".<target>.<random>.tmp" next to the target
_TEMPORARY = re.compile(r"^\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp$")


class CheckpointError(ValueError):
    """A checkpoint that is missing, damaged, of another format, or not the one that was expected."""


@dataclass(frozen=True)
class Checkpoint:
    """A verified checkpoint: ``state`` (what was saved), ``meta`` (JSON), the file and its format version."""

    path: Path
    state: dict
    meta: dict
    format_version: int = FORMAT_VERSION


# ----------------------------------------------------------------------------------------- saving


def _plain(obj: Any, where: str = "state") -> Any:
    """``obj`` as containers ``torch.load(weights_only=True)`` reads back: numpy scalars become Python
    numbers, Mapping / tuple subclasses become dict / tuple; anything else unsupported raises TypeError
    naming where it is."""
    import torch

    if obj is None or type(obj) in (bool, int, float, str, bytes) or isinstance(obj, (torch.Tensor, torch.dtype, torch.device, torch.Size)):
        return obj
    if isinstance(obj, np.generic) and obj.dtype.kind in "biuf":
        return obj.item()
    for base in (bool, int, float, str, bytes):  # subclasses (IntEnum, numpy float64, ...)
        if isinstance(obj, base):
            return base(obj)
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if type(key) not in (str, int):
                raise TypeError(f"save_checkpoint: {where} has a key of type {type(key).__name__} ({key!r}); use str or int keys")
            out[key] = _plain(value, f"{where}[{key!r}]")
        return out
    if isinstance(obj, (list, tuple)):
        items = [_plain(value, f"{where}[{i}]") for i, value in enumerate(obj)]
        return items if isinstance(obj, list) else tuple(items)
    raise TypeError(
        f"save_checkpoint: {where} is a {type(obj).__module__}.{type(obj).__qualname__}; a checkpoint state holds only "
        "tensors, numbers, strings, bytes, None and dict/list/tuple of those (convert numpy arrays with torch.from_numpy)"
    )


def _fsync_directory(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def save_checkpoint(path: str | os.PathLike, state: Mapping[str, Any], *, meta: Mapping[str, Any]) -> Path:
    """Write ``state`` and ``meta`` to ``path`` atomically; return the path.

    Args:
        state: what to restore later (``state_dict()`` s, RNG states from :func:`capture_rng_state`,
            counters, metrics so far): dicts/lists/tuples of tensors, numbers, strings, bytes, None.
        meta: JSON-serialisable description checked by ``load_checkpoint(expect=...)``. Every recipe
            writes at least ``kind`` ("dynamics", "agent"), ``preset``, ``task`` (env id) and ``config``
            (the resolved Hydra config).

    The bytes go to a temporary file in the same folder, are flushed and fsync'ed, then renamed onto
    ``path`` and the folder is fsync'ed: a kill or a full disk leaves the previous checkpoint (and at
    worst a ``.checkpoint.pt.*.tmp`` file that :func:`clean_stale_temporaries` removes).
    """
    import torch

    if not isinstance(state, Mapping):
        raise TypeError(f"save_checkpoint: state must be a mapping, got {type(state).__name__}")
    if "kind" not in meta:
        raise ValueError("save_checkpoint: meta must contain 'kind' (e.g. 'dynamics', 'agent')")
    state = _plain(state)
    try:
        meta_bytes = json.dumps(dict(meta), sort_keys=True, allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as err:
        raise TypeError(f"save_checkpoint: meta must be JSON-serialisable (finite numbers): {err}") from err
    buffer = io.BytesIO()
    torch.save(state, buffer)
    state_bytes = buffer.getbuffer()  # no copy: a paper-preset checkpoint with Adam is ~600 MB
    digest = hashlib.sha256(meta_bytes)
    digest.update(state_bytes)
    header = {"format_version": FORMAT_VERSION, "meta_bytes": len(meta_bytes), "state_bytes": len(state_bytes),
              "sha256": digest.hexdigest()}
    header_bytes = json.dumps(header, sort_keys=True).encode("ascii") + b"\n"

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        if hasattr(os, "fchmod"):  # the permissions of an ordinary file (mkstemp's are owner-only)
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            for chunk in (MAGIC, header_bytes, meta_bytes, state_bytes):
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_directory(path.parent)
    return path


# ---------------------------------------------------------------------------------------- loading


def _resolve_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: no such file")
    return path


def _read_header(path: Path, f) -> tuple[dict, int]:
    """(header, offset of the meta bytes) of an open checkpoint file; CheckpointError if it is not one."""
    magic = f.read(len(MAGIC))
    if magic != MAGIC:
        if magic.startswith(b"PK\x03\x04"):
            raise CheckpointError(
                f"checkpoint {path}: a plain torch.save file, not an ldm_rl checkpoint (written before the checkpoint "
                "format, no checksum); load it with torch.load(..., weights_only=False) only if you trust it"
            )
        raise CheckpointError(f"checkpoint {path}: not an ldm_rl checkpoint (the file does not start with {MAGIC!r})")
    line = f.readline(_MAX_HEADER)
    try:
        header = json.loads(line.decode("ascii"))
        version = header["format_version"]
        sizes = int(header["meta_bytes"]), int(header["state_bytes"])
        str(header["sha256"])
    except (UnicodeDecodeError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"checkpoint {path}: damaged header line ({type(err).__name__}): the file is corrupted") from err
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path}: format version {version!r}, this ldm_rl reads version {FORMAT_VERSION} "
            "(written by another ldm_rl version?)"
        )
    if min(sizes) < 0:
        raise CheckpointError(f"checkpoint {path}: damaged header line (negative sizes): the file is corrupted")
    return header, len(MAGIC) + len(line)


def _lookup(meta: Mapping[str, Any], dotted: str) -> tuple[bool, Any]:
    node: Any = meta
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False, None
        node = node[part]
    return True, node


def check_meta(meta: Mapping[str, Any], expect: Mapping[str, Any] | None, *, path: str | os.PathLike = "checkpoint") -> None:
    """Raise CheckpointError at the first ``expect`` key (dotted keys reach into nested meta, e.g.
    ``"config.env.num_rotations"``) whose value in ``meta`` differs."""
    for key, wanted in (expect or {}).items():
        found, value = _lookup(meta, key)
        if not found:
            raise CheckpointError(f"checkpoint {path}: has no {key!r} field, expected {key}={wanted!r}")
        if value != wanted:
            raise CheckpointError(f"checkpoint {path}: {key} is {value!r}, expected {wanted!r}")


def read_checkpoint_meta(path: str | os.PathLike, *, verify: bool = False) -> dict:
    """The meta of a checkpoint without loading its state (and without importing torch).

    ``verify=True`` also checks the file size and the checksum (reads the whole file).
    """
    path = _resolve_file(path)
    with open(path, "rb") as f:
        if verify:
            meta_bytes, _, _ = _read_verified(path, f)
        else:
            header, _ = _read_header(path, f)
            meta_bytes = f.read(header["meta_bytes"])
            if len(meta_bytes) < header["meta_bytes"]:
                raise CheckpointError(f"checkpoint {path}: truncated: the meta ends after {len(meta_bytes):,} of "
                                      f"{header['meta_bytes']:,} bytes")
    return _decode_meta(path, meta_bytes)


def _decode_meta(path: Path, meta_bytes: bytes) -> dict:
    try:
        meta = json.loads(meta_bytes.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {path}: damaged meta ({type(err).__name__}): the file is corrupted") from err
    if not isinstance(meta, dict):
        raise CheckpointError(f"checkpoint {path}: damaged meta (not a JSON object): the file is corrupted")
    return meta


def _read_verified(path: Path, f) -> tuple[bytes, bytes, dict]:
    """(meta bytes, state bytes, header) of the open checkpoint ``f``, after the size and checksum checks."""
    header, offset = _read_header(path, f)
    size = os.fstat(f.fileno()).st_size
    expected = offset + header["meta_bytes"] + header["state_bytes"]
    if size != expected:
        what = "truncated" if size < expected else "has extra bytes"
        raise CheckpointError(f"checkpoint {path}: {what}: {size:,} bytes, the header says {expected:,}")
    meta_bytes, state_bytes = f.read(header["meta_bytes"]), f.read(header["state_bytes"])
    digest = hashlib.sha256(meta_bytes)
    digest.update(state_bytes)
    if digest.hexdigest() != header["sha256"]:
        raise CheckpointError(
            f"checkpoint {path}: checksum mismatch (SHA-256 {digest.hexdigest()[:16]}…, the header says "
            f"{str(header['sha256'])[:16]}…): the file is corrupted; use an earlier checkpoint or rerun"
        )
    return meta_bytes, state_bytes, header


def load_checkpoint(
    path: str | os.PathLike,
    *,
    expect: Mapping[str, Any] | None = None,
    map_location: Any = "cpu",
    weights_only: bool = True,
) -> Checkpoint:
    """Read and verify a checkpoint written by :func:`save_checkpoint` (or a run folder holding
    ``checkpoint.pt``).

    Verifies, in this order, each failure being one :class:`CheckpointError` naming the file: that it
    exists, the magic line and header, the format version, the size, the SHA-256 of meta + state,
    then every ``expect`` key against the meta (e.g. ``{"kind": "dynamics", "preset": "lite",
    "task": "ldm_rl/BlockStacking-v0"}``). The state is loaded with ``torch.load(weights_only=True)``
    onto ``map_location``.
    """
    import torch

    path = _resolve_file(path)
    with open(path, "rb") as f:
        meta_bytes, state_bytes, header = _read_verified(path, f)
    meta = _decode_meta(path, meta_bytes)
    check_meta(meta, expect, path=path)
    try:
        state = torch.load(io.BytesIO(state_bytes), map_location=map_location, weights_only=weights_only)
    except Exception as err:  # checksum passed: a state this torch cannot read
        raise CheckpointError(f"checkpoint {path}: the state does not load with this torch ({type(err).__name__}: "
                              f"{str(err).splitlines()[0] if str(err) else ''})") from err
    return Checkpoint(path=path, state=state, meta=meta, format_version=header["format_version"])


# ------------------------------------------------------------------------------------------- RNGs


def _pack(obj: Any) -> Any:
    """numpy arrays inside an RNG state -> {"__ndarray__": tensor, "dtype": str} (weights_only-loadable)."""
    import torch

    if isinstance(obj, np.ndarray):
        return {"__ndarray__": torch.from_numpy(obj.astype(np.int64) if obj.dtype.kind in "ui" else obj.copy()),
                "dtype": str(obj.dtype)}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _pack(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_pack(v) for v in obj)
    return obj


def _unpack(obj: Any) -> Any:
    if isinstance(obj, dict):
        if "__ndarray__" in obj:
            return obj["__ndarray__"].cpu().numpy().astype(obj["dtype"])
        return {k: _unpack(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_unpack(v) for v in obj)
    return obj


def capture_rng_state(generators: Mapping[str, Any] | None = None) -> dict:
    """Every RNG state a run depends on: python ``random``, numpy's global RNG, torch's CPU RNG, every
    CUDA device's RNG (when CUDA is initialised), and each generator in ``generators`` by name
    (``torch.Generator``, ``numpy.random.Generator`` / ``RandomState`` or ``random.Random``, e.g. the
    data sampler's or an env's). The result can go into a checkpoint state as is."""
    import torch

    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": _pack(np.random.get_state(legacy=False)),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = list(torch.cuda.get_rng_state_all())
    named = {}
    for name, gen in (generators or {}).items():
        if isinstance(gen, torch.Generator):
            named[name] = {"type": "torch", "device": str(gen.device), "state": gen.get_state()}
        elif isinstance(gen, np.random.Generator):
            named[name] = {"type": "numpy", "state": _pack(gen.bit_generator.state)}
        elif isinstance(gen, np.random.RandomState):
            named[name] = {"type": "numpy_legacy", "state": _pack(gen.get_state(legacy=False))}
        elif isinstance(gen, random.Random):
            named[name] = {"type": "python", "state": gen.getstate()}
        else:
            raise TypeError(f"capture_rng_state: generator {name!r} is a {type(gen).__name__}, not a torch/numpy/python RNG")
    state["generators"] = named
    return state


def restore_rng_state(state: Mapping[str, Any], generators: Mapping[str, Any] | None = None) -> None:
    """Put back what :func:`capture_rng_state` captured, into the global RNGs and into each of
    ``generators`` (matched by name; a name the state lacks raises ValueError)."""
    import torch

    random.setstate(state["python"])
    np.random.set_state(_unpack(state["numpy"]))
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
    saved = state.get("generators", {})
    for name, gen in (generators or {}).items():
        if name not in saved:
            raise ValueError(f"restore_rng_state: the saved state has no generator {name!r} (it has {sorted(saved)})")
        entry = saved[name]
        if isinstance(gen, torch.Generator) and entry["type"] == "torch":
            gen.set_state(entry["state"].cpu())
        elif isinstance(gen, np.random.Generator) and entry["type"] == "numpy":
            gen.bit_generator.state = _unpack(entry["state"])
        elif isinstance(gen, np.random.RandomState) and entry["type"] == "numpy_legacy":
            gen.set_state(_unpack(entry["state"]))
        elif isinstance(gen, random.Random) and entry["type"] == "python":
            gen.setstate(entry["state"])
        else:
            raise ValueError(f"restore_rng_state: generator {name!r} is a {type(gen).__name__}, the state holds a {entry['type']} one")


# ---------------------------------------------------------------------------------- stale files


def clean_stale_temporaries(directory: str | os.PathLike) -> list[Path]:
    """Remove what a kill during a save left in ``directory`` (not recursive); return the removed paths.

    Removes ``.NAME.<random>.tmp`` files and folders (``save_checkpoint`` and ``outputs.atomic_path``
    temporaries) and ``.NAME.old`` folders of ``atomic_path`` whose ``NAME`` exists; a ``.NAME.old``
    whose ``NAME`` is missing (a kill between the two renames of a folder replacement) is moved back
    to ``NAME``. Call it at the start of a run, on a folder no other process is writing to.
    """
    directory = Path(directory)
    removed: list[Path] = []
    if not directory.is_dir():
        return removed
    for entry in sorted(directory.iterdir()):
        name = entry.name
        if _TEMPORARY.match(name):
            target = entry
        elif name.startswith(".") and name.endswith(".old") and len(name) > 5 and entry.is_dir():
            original = directory / name[1:-4]
            if not original.exists():
                os.replace(entry, original)
                removed.append(entry)
                continue
            target = entry
        else:
            continue
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target, ignore_errors=True)
        else:
            target.unlink(missing_ok=True)
        removed.append(target)
    return removed
