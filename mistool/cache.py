"""The table cache: tracked motion tables stored column by column, resumable, bounded.

``mistool serve`` tracks a sequence once and keeps the result here, so that the next launch
of the unchanged sequence shows it at once, and a tracking run stopped half-way resumes where
it stopped. Nothing here imports viser; nothing is ever written beside the sequence.

Layout of one entry, ``<root>/<key>/``::

    meta.json          what the entry is (key inputs, frames, chunks done, complete or not)
    frames.json        the frame file names in frame order (a folder; for the viewer)
    raw/<a>-<b>.npz    raw (unrefined) rows of frames [a, b), one file per tracked chunk
    state-<b>.pkl      the tracker's state after the last chunk, frames [.., b) (to
                       resume from there; the previous one goes once the chunk is listed)
    final/<col>.npy    the finished, refined table: one .npy per column (memory-mapped)

Columns are plain numpy arrays (no pickle): numbers as float64/int64, text (``instrument``,
``part``, ``pose_status``) as int32 codes into a small array of distinct values. Loading a
finished 90,000-frame table memory-maps its columns (``scripts/bench_live.py`` measures
it). Every file is written to a
temporary name and renamed, so a run killed at any moment leaves a readable entry.

**Key** (:func:`cache_key`): a digest of mistool's version, the sequence's resolved path,
every frame file's name (a video: its own), the effective config, and the tracking options.
Change any of them and the entry is another one. The files' sizes and modification times
are digested apart (:func:`frames_digest`, stored in ``meta.json``): stored rows are reused
only when that digest is the files' digest now (a touched frame empties the entry).

**Size policy** (:func:`enforce_limit`): the cache holds at most ``MISTOOL_CACHE_MAX_BYTES``
bytes (default :data:`DEFAULT_MAX_BYTES`); when it is over, whole entries are removed, least
recently used first (an entry is "used" when opened), never the entry in use.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import pickle
import shutil
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mistool.config import Config
from mistool.errors import InputPathError, TableError
from mistool.model import COLUMN_DTYPES, TrackTable

#: Default upper bound of the whole cache (bytes), overridden by ``MISTOOL_CACHE_MAX_BYTES``.
DEFAULT_MAX_BYTES = 2_000_000_000
#: Environment variable holding the cache's size bound in bytes.
MAX_BYTES_ENV = "MISTOOL_CACHE_MAX_BYTES"
#: Version of the on-disk layout (part of every key).
FORMAT_VERSION = 3


def cache_root() -> Path:
    """Where tables are cached: ``$XDG_CACHE_HOME/mistool/tables`` (default
    ``~/.cache/mistool/tables``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "mistool" / "tables"


def cache_key(
    seq_path: Path, config: Config, files: Iterable[Path | os.DirEntry[str]], **options: Any
) -> str:
    """A digest of what names a tracked table: mistool's version, the sequence, its frame
    files' names in order, the config and the tracking options. The files' contents are
    checked apart (:func:`frames_digest`, stored in the entry): listing 100,000 names is
    quick, ``stat``-ing them all is not, and need not delay tracking's first frames.

    Args:
        seq_path: the sequence folder or mask video.
        config: the effective config (after ``mistool.toml`` and command-line options).
        files: the frame files in frame order (a video: the video itself), as paths or
            directory entries (:func:`mistool.sequence.scan_frames`).
        **options: tracking options (e.g. ``metric=True, smoothing="offline"``).
    """
    from mistool import __version__

    h = hashlib.sha256(f"{__version__}\n{FORMAT_VERSION}\n{seq_path.resolve()}\n".encode())
    h.update(repr(config).encode())
    h.update(json.dumps(options, sort_keys=True, default=str).encode())
    h.update("\n".join(f.name for f in files).encode())
    return h.hexdigest()[:32]


class FramesDigest:
    """A digest of frame files' sizes and modification times, fed in frame order (with
    :func:`cache_key`'s names: what the old single key covered). A stored run is reused
    only when the digest stored with it is the files' digest now."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def add(self, files: Iterable[Path | os.DirEntry[str]]) -> None:
        """Stat ``files`` (the next ones in frame order) into the digest.

        Raises:
            InputPathError: a file cannot be stat'ed (e.g. a dangling symlink).
        """
        for f in files:
            try:
                st = f.stat()
            except OSError as exc:
                raise InputPathError(_unreadable(str(getattr(f, "path", f)), exc)) from None
            self._h.update(f"{st.st_size}\t{st.st_mtime_ns}\n".encode())

    def hexdigest(self) -> str:
        """The digest so far."""
        return self._h.hexdigest()[:32]


def _unreadable(path: str, exc: OSError) -> str:
    """One line for a frame file that cannot be stat'ed."""
    if exc.errno == errno.ELOOP:
        return f"{path}: cannot read this frame: symlink loop"
    if os.path.islink(path):
        return f"{path}: cannot read this frame: dangling symlink to {os.readlink(path)}"
    return f"{path}: cannot read this frame: {exc.strerror or exc}"


def frames_digest(files: Iterable[Path | os.DirEntry[str]]) -> str:
    """:class:`FramesDigest` of ``files`` (all of them, in frame order)."""
    digest = FramesDigest()
    digest.add(files)
    return digest.hexdigest()


# -- columns <-> numpy -------------------------------------------------------------------
#: Suffixes of the two arrays storing a text column: codes (int32) and distinct values.
_CODES, _NAMES = "@codes", "@names"


def _encode(table: TrackTable) -> dict[str, np.ndarray]:
    """Numeric columns as they are; text columns as ``<name>@codes`` (int32) and
    ``<name>@names`` (unicode), so that no pickle is needed and loading is an index."""
    out: dict[str, np.ndarray] = {}
    for name in table.columns:
        col = np.asarray(table[name])
        if col.dtype == object:
            names, codes = np.unique(col.astype(str), return_inverse=True)
            out[name + _CODES] = codes.reshape(-1).astype(np.int32)
            out[name + _NAMES] = names
        else:
            out[name] = col
    return out


def _decode(columns: dict[str, np.ndarray]) -> TrackTable:
    cols: dict[str, np.ndarray] = {}
    for key, arr in columns.items():
        if key.endswith(_NAMES):
            continue
        if key.endswith(_CODES):  # one str object per distinct value, shared by rows
            name = key[: -len(_CODES)]
            lut = np.empty(len(columns[name + _NAMES]), dtype=object)
            lut[:] = [str(v) for v in columns[name + _NAMES]]
            cols[name] = lut[np.asarray(arr)]
        else:
            dtype = COLUMN_DTYPES.get(key)
            cols[key] = arr if dtype is None or dtype is object else arr.astype(dtype, copy=False)
    return TrackTable(cols)


def _atomic_bytes(path: Path, write: Any) -> None:
    """Write a file through ``write(file_object)`` to a temporary name, then rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@dataclass
class Progress:
    """How far tracking into an entry has got."""

    done: int
    """Frames tracked (rows stored for frames ``[0, done)``)."""
    total: int | None
    """Frames in the sequence (None when unknown)."""
    complete: bool
    """The refined table is stored."""
    chunks: list[tuple[int, int]]
    """Stored raw chunks, ``[a, b)`` frame ranges in order."""
    error: str | None = None
    """The one-line error that stopped tracking, if any."""


class CacheEntry:
    """One cached table (see the module docstring for the layout)."""

    def __init__(self, root: Path, key: str) -> None:
        self.path = root / key
        """The entry's folder."""
        self.key = key

    # -- meta ---------------------------------------------------------------------------
    def _meta(self) -> dict[str, Any]:
        try:
            return json.loads((self.path / "meta.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}

    def _write_meta(self, meta: dict[str, Any]) -> None:
        data = json.dumps(meta, indent=1).encode()
        _atomic_bytes(self.path / "meta.json", lambda f: f.write(data))

    def progress(self) -> Progress:
        """What is stored (nothing yet: ``done == 0``)."""
        meta = self._meta()
        chunks = [(int(a), int(b)) for a, b in meta.get("chunks", [])]
        return Progress(
            done=chunks[-1][1] if chunks else 0,
            total=meta.get("total"),
            complete=bool(meta.get("complete")) and (self.path / "final").is_dir(),
            chunks=chunks,
            error=meta.get("error"),
        )

    def begin(self, total: int | None, info: dict[str, Any]) -> None:
        """Create the entry (or keep what it has) and mark it used."""
        self.path.mkdir(parents=True, exist_ok=True)
        meta = self._meta()
        meta.setdefault("chunks", [])
        meta.update(total=total, info=info, format=FORMAT_VERSION, error=None)
        self._write_meta(meta)
        self.touch()

    def touch(self) -> None:
        """Mark the entry as used now (the size policy removes the least recently used)."""
        with contextlib.suppress(OSError):
            (self.path / "used").write_text(f"{time.time():.3f}\n")

    def last_used(self) -> float:
        """When the entry was last used (seconds since the epoch; 0 if unknown)."""
        try:
            return (self.path / "used").stat().st_mtime
        except OSError:
            return 0.0

    # -- the frames -------------------------------------------------------------------
    def frames_digest(self) -> str | None:
        """The :func:`frames_digest` of the files the stored rows come from (None: not
        stored yet, e.g. a run stopped before it was: then nothing stored is reused)."""
        value = self._meta().get("frames")
        return value if isinstance(value, str) else None

    def set_frames_digest(self, digest: str) -> None:
        """Store the digest of the files the rows come from."""
        meta = self._meta()
        meta["frames"] = digest
        self._write_meta(meta)

    def write_frame_names(self, names: list[str]) -> None:
        """Store the sequence's frame file names in frame order (``frames.json``), for the
        viewer, which then need not list a long folder itself."""
        self.path.mkdir(parents=True, exist_ok=True)
        data = json.dumps(list(names)).encode()
        _atomic_bytes(self.path / "frames.json", lambda f: f.write(data))

    def frame_names(self) -> list[str] | None:
        """The frame file names stored by :meth:`write_frame_names` (None: not stored)."""
        try:
            names = json.loads((self.path / "frames.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return [str(n) for n in names] if isinstance(names, list) else None

    # -- raw chunks ---------------------------------------------------------------------
    def add_chunk(self, start: int, stop: int, table: TrackTable, state: Any = None) -> None:
        """Store the raw rows of frames ``[start, stop)`` (and the tracker's state after
        them, to resume from); chunks must follow each other."""
        done = self.progress().done
        if start != done:
            raise TableError(f"{self.path}: chunk starts at frame {start}, expected {done}")
        cols = _encode(table)
        _atomic_bytes(
            self.path / "raw" / f"{start:08d}-{stop:08d}.npz",
            lambda f: np.savez(f, **cols),  # type: ignore[arg-type]
        )
        if state is not None:  # beside the previous state: a run killed before the
            # chunk is listed below resumes from that one, not from the start
            data = pickle.dumps((stop, state))
            _atomic_bytes(self._state_path(stop), lambda f: f.write(data))
        meta = self._meta()
        meta["chunks"] = [*meta.get("chunks", []), [start, stop]]
        self._write_meta(meta)
        self._drop_states(keep=self._state_path(stop))

    def read_chunk(self, start: int, stop: int) -> TrackTable:
        """The raw rows of one stored chunk."""
        with np.load(self.path / "raw" / f"{start:08d}-{stop:08d}.npz") as z:
            return _decode({k: z[k] for k in z.files})

    def read_raw(self) -> TrackTable:
        """Every stored raw row, in frame order."""
        return TrackTable.concat([self.read_chunk(a, b) for a, b in self.progress().chunks])

    def state(self, at: int) -> Any:
        """The tracker state stored after frame ``at - 1``, or None (no or another state)."""
        for path in (self._state_path(at), self.path / "state.pkl"):  # (an older layout)
            try:
                stop, state = pickle.loads(path.read_bytes())
            except (OSError, pickle.UnpicklingError, EOFError, ValueError, AttributeError):
                continue
            if stop == at:
                return state
        return None

    def _state_path(self, stop: int) -> Path:
        return self.path / f"state-{stop:08d}.pkl"

    def _drop_states(self, keep: Path | None = None) -> None:
        for path in [*self.path.glob("state-*.pkl"), self.path / "state.pkl"]:
            if path != keep:
                with contextlib.suppress(OSError):
                    path.unlink()

    def fail(self, message: str) -> None:
        """Record the error that stopped tracking."""
        meta = self._meta()
        meta["error"] = message
        self._write_meta(meta)

    # -- the finished table -------------------------------------------------------------
    def finish(self, table: TrackTable) -> None:
        """Store the refined table (one .npy per column) and mark the entry complete; the
        raw chunks and state are removed."""
        tmp = Path(tempfile.mkdtemp(dir=self.path, prefix=".final."))
        try:
            cols = _encode(table)
            for name, arr in cols.items():
                np.save(tmp / f"{name}.npy", arr)
            (tmp / "columns.json").write_text(json.dumps(list(cols)), encoding="utf-8")
            final = self.path / "final"
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        meta = self._meta()
        meta["complete"] = True
        self._write_meta(meta)
        shutil.rmtree(self.path / "raw", ignore_errors=True)
        self._drop_states()

    def read_final(self, mmap: bool = True) -> TrackTable:
        """The finished table; numeric columns memory-mapped (read on demand) by default.

        Raises:
            TableError: the entry is not complete or is damaged.
        """
        final = self.path / "final"
        try:
            names = json.loads((final / "columns.json").read_text(encoding="utf-8"))
            cols = {
                n: np.load(final / f"{n}.npy", mmap_mode="r" if mmap else None, allow_pickle=False)
                for n in names
            }
        except (OSError, ValueError) as exc:
            raise TableError(f"{final}: damaged cache entry ({exc})") from None
        return _decode(cols)

    def size_bytes(self) -> int:
        """Bytes on disk."""
        total = 0
        for p in self.path.rglob("*"):
            with contextlib.suppress(OSError):
                if p.is_file():
                    total += p.stat().st_size
        return total

    def remove(self) -> None:
        """Delete the entry."""
        shutil.rmtree(self.path, ignore_errors=True)


def max_bytes() -> int:
    """The cache's size bound (bytes): ``MISTOOL_CACHE_MAX_BYTES`` or the default."""
    try:
        return max(0, int(os.environ.get(MAX_BYTES_ENV, DEFAULT_MAX_BYTES)))
    except ValueError:
        return DEFAULT_MAX_BYTES


def entries(root: Path | None = None) -> list[CacheEntry]:
    """Every entry of the cache, least recently used first."""
    root = root or cache_root()
    if not root.is_dir():
        return []
    found = [CacheEntry(root, p.name) for p in root.iterdir() if p.is_dir()]
    return sorted(found, key=lambda e: e.last_used())


def enforce_limit(keep: CacheEntry | None = None, limit: int | None = None) -> list[str]:
    """Remove least recently used entries until the cache is within ``limit`` bytes
    (default :func:`max_bytes`); ``keep`` is never removed. Returns the removed keys."""
    limit = max_bytes() if limit is None else limit
    root = keep.path.parent if keep is not None else None
    found = entries(root)
    sizes = {e.key: e.size_bytes() for e in found}
    total = sum(sizes.values())
    removed = []
    for e in found:
        if total <= limit:
            break
        if keep is not None and e.key == keep.key:
            continue
        e.remove()
        total -= sizes[e.key]
        removed.append(e.key)
    return removed


def open_entry(key: str, root: Path | None = None) -> CacheEntry:
    """The entry for ``key`` (not created yet until :meth:`CacheEntry.begin`)."""
    return CacheEntry(root or cache_root(), key)


__all__ = [
    "DEFAULT_MAX_BYTES",
    "CacheEntry",
    "Progress",
    "cache_key",
    "cache_root",
    "enforce_limit",
    "entries",
    "max_bytes",
    "open_entry",
]
