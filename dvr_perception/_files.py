"""Atomic output files: PNG images, JSON documents and ``.npz`` buffer archives.

Every writer goes through :func:`atomic_path`: the data is written to a hidden temporary file
in the target's directory and moved over the target with :func:`os.replace` only when writing
succeeded, so an interrupted or failed write never leaves a partial file behind.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import shutil
import signal
import stat
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "LOCK_NAME",
    "StagedFolder",
    "Terminated",
    "atomic_path",
    "check_distinct",
    "check_target",
    "check_writable",
    "commit",
    "file_lock",
    "file_mode",
    "json_ready",
    "output_folder",
    "png_bytes",
    "read_png",
    "staged_files",
    "terminate_as_interrupt",
    "write_json",
    "write_npz",
    "write_png",
]


@contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` if the block succeeds.

    The temporary file does not exist when the block starts; the caller creates it.  If the
    block raises, the temporary file (if any) is removed and ``path`` is left untouched.  An
    ``OSError`` about the temporary file is raised again naming ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The final file.  Its directory must exist; if it exists it must be a regular file.

    Yields
    ------
    pathlib.Path
        A hidden file name in the same directory, with the same suffix as ``path``.

    Raises
    ------
    DVRInputError
        If the directory of ``path`` does not exist or ``path`` exists and is not a regular
        file (a directory, device or pipe).

    Examples
    --------
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "hello.txt"
    >>> with atomic_path(target) as tmp:
    ...     _ = tmp.write_text("hi")
    >>> target.read_text()
    'hi'
    """
    final = check_target(path)
    tmp = final.parent / f".{final.name}.{secrets.token_hex(4)}.tmp{final.suffix}"
    try:
        try:
            yield tmp
            if not tmp.exists():
                raise OSError(f"output file {final}: nothing was written")
            os.replace(tmp, final)
        except OSError as exc:
            if exc.filename is not None and exc.strerror:  # name the file, not the temporary
                raise OSError(exc.errno, exc.strerror, str(final)) from None
            raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_target(path) -> Path:
    """Return ``path`` as a Path if it may be written; refuse a non-regular existing target.

    Examples
    --------
    >>> check_target("/dev/null")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: output file /dev/null: exists and is not a regular file (a device, folder or pipe); refusing to replace it
    """  # noqa: E501
    final = Path(path)
    parent = final.parent
    if not parent.is_dir():
        raise DVRInputError(f"output file {final}: directory {parent} does not exist")
    try:
        st = os.stat(final)
    except (FileNotFoundError, NotADirectoryError):
        return final
    except OSError as exc:
        raise DVRInputError(f"output file {final}: cannot check it ({exc.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise DVRInputError(f"output file {final}: is a directory; expected a file name")
    if not stat.S_ISREG(st.st_mode):
        raise DVRInputError(
            f"output file {final}: exists and is not a regular file (a device, folder or pipe); "
            "refusing to replace it"
        )
    return final


#: A folder must have this much free space before a run writes into it.
MIN_FREE_BYTES = 2**20


def check_writable(folder, what: str = "output folder") -> Path:
    """Fail early, naming ``folder``, when no file can be created in it (or it is full).

    A probe file is created and removed at once; nothing is left behind.

    Examples
    --------
    >>> import tempfile
    >>> check_writable(tempfile.mkdtemp()).is_dir()
    True
    """
    folder = Path(folder) if str(folder) else Path(".")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
        st = os.statvfs(folder)
    except OSError as exc:
        raise DVRInputError(
            f"{what} {folder}: cannot write into it ({exc.strerror or exc})"
        ) from None
    if st.f_bavail * st.f_frsize < MIN_FREE_BYTES:
        raise DVRInputError(f"{what} {folder}: the file system is full")
    return folder


def check_distinct(paths: Mapping[str, object]) -> None:
    """Refuse two outputs that name the same file (``{option: path}``; ``None`` skipped).

    Examples
    --------
    >>> check_distinct({"--out": "x.png", "--buffers": "./x.png"})
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: --buffers x.png: the same file as --out x.png; give each output its own path
    """  # noqa: E501
    seen: dict[Path, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        key = Path(os.path.abspath(path))
        if key.exists() or key.parent.exists():
            key = key.parent.resolve() / key.name
        if key in seen:
            raise DVRInputError(
                f"{option} {Path(path)}: the same file as {seen[key]}; give each output its "
                "own path"
            )
        seen[key] = f"{option} {Path(path)}"


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """Return the mode of a new output file: ``0o666`` less the umask (0644 under umask 022)."""
    return 0o666 & ~_umask()


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread by :func:`terminate_as_interrupt`'s handler.

    A :class:`KeyboardInterrupt`, so every clean-up that runs for Ctrl-C (staged files and
    folders removed, locks released) runs for SIGTERM too.
    """


#: Signals held back while outputs are moved into place or cleaned up.
_HELD = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """While active, SIGTERM raises :class:`Terminated` in the main thread (once).

    The default action of SIGTERM ends the process at once, leaving a lock file and a staging
    folder behind; raised as an exception it unwinds like Ctrl-C.  Further SIGTERMs during
    that unwinding are ignored (the process is already ending).  Nothing changes outside the
    main thread or where SIGTERM already has a Python handler (e.g. the web app's).

    Examples
    --------
    >>> with terminate_as_interrupt():
    ...     try:
    ...         signal.raise_signal(signal.SIGTERM)
    ...     except Terminated:
    ...         print("terminated")
    terminated
    """
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(
        signal.SIGTERM
    ) not in (signal.SIG_DFL, None):
        yield
        return
    fired: list = []

    def handler(signum, frame):
        if not fired:
            fired.append(signum)
            raise Terminated

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGTERM) is handler:  # else the caller chose (e.g. SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_DFL if old is None else old)


@contextmanager
def _deferred_sigint() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) and SIGTERM back during the block and deliver them afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = [s for s in _HELD if signal.getsignal(s) is not None]  # None: a C handler (pvpython)
    caught: list = []
    old = {s: signal.signal(s, lambda signum, frame: caught.append((signum, frame))) for s in held}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
    for signum, frame in caught:
        handler = old[signum]
        if callable(handler):
            handler(signum, frame)
        elif handler == signal.SIG_DFL:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            signal.raise_signal(signum)  # the default action, now that the files are in place


def commit(moves, remove=()) -> None:
    """Move every ``(staged, final)`` pair into place, all or none, Ctrl-C held back.

    Every target is checked first (a non-regular existing target refuses the whole set), then
    the renames run with SIGINT and SIGTERM deferred, so an interrupt leaves either all files
    or none.  The regular files among ``remove`` (outputs of an earlier run that these files
    make stale) are deleted in the same step.
    """
    moves = [(Path(a), Path(b)) for a, b in moves]
    for _, final in moves:
        check_target(final)
    stale = [p for p in map(Path, remove) if p.is_file() and not p.is_symlink()]
    with _deferred_sigint():
        for staged, final in moves:
            os.replace(staged, final)
        for p in stale:
            p.unlink(missing_ok=True)


@contextmanager
def staged_files(*paths) -> Iterator[list[Path]]:
    """Yield a hidden temporary path beside each of ``paths``; move them all in at the end.

    The caller writes every temporary file; when the block succeeds they are moved onto
    ``paths`` together (:func:`commit`), else removed: all files or none.

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> with staged_files(d / "a.txt", d / "b.txt") as (a, b):
    ...     _ = a.write_text("a"), b.write_text("b")
    >>> sorted(p.name for p in d.iterdir())
    ['a.txt', 'b.txt']
    """
    finals = [check_target(p) for p in paths]
    token = secrets.token_hex(4)
    tmps = [f.parent / f".{f.name}.{token}.part{f.suffix}" for f in finals]
    try:
        yield tmps
        for t, f in zip(tmps, finals, strict=True):
            if not t.is_file():
                raise OSError(f"output file {f}: nothing was written")
        commit(zip(tmps, finals, strict=True))
    finally:
        for t in tmps:
            t.unlink(missing_ok=True)


class StagedFolder:
    """A staging folder inside an output folder; see :func:`output_folder`."""

    def __init__(self, final: Path, staging: Path) -> None:
        self.final = final
        self.path = staging

    def final_path(self, path) -> Path:
        """Return where the staged ``path`` ends up."""
        p = Path(path)
        try:
            return self.final / p.relative_to(self.path)
        except ValueError:
            return p

    def publish(self, stale=()) -> list[Path]:
        """Move the files staged so far into the folder now (all or none); keep the lock.

        For outputs in two steps: the first (a result) appears while the second (e.g. its
        figures) is still being written into the staging folder; an interrupt or error in the
        second step leaves the first in place and removes only what the second staged.
        ``stale`` names files of the folder (relative to it) that an earlier run wrote and
        that the second step will write again: they are removed with the move, so the folder
        never mixes this run's result with an earlier run's figures.

        Returns
        -------
        list of pathlib.Path
            The files moved, at their final paths.
        """
        return _publish(self.final, self.path, [self.final / Path(p).name for p in stale])

    def relocate(self, obj):
        """Return ``obj`` (JSON-like) with staged paths in its strings pointing to the folder."""
        if isinstance(obj, str):
            return obj.replace(str(self.path), str(self.final))
        if isinstance(obj, dict):
            return {k: self.relocate(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return [self.relocate(v) for v in obj]
        return obj


LOCK_NAME = ".dvr-perception.lock"


def _lock(final: Path, lock: Path | None = None, what: str | None = None):
    """Take a lock file (the output folder's by default); return its descriptor (non-blocking).

    ``lock`` is the lock file (``final / LOCK_NAME`` by default) and ``what`` names the target
    in the errors (``"output folder FINAL"`` by default).
    """
    lock = final / LOCK_NAME if lock is None else lock
    what = f"output folder {final}" if what is None else what
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DVRInputError(
                f"{what}: cannot create the lock file {lock} ({exc.strerror})"
            ) from None
        try:
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except (BlockingIOError, FileNotFoundError) as exc:
            os.close(fd)
            if isinstance(exc, FileNotFoundError):
                continue  # the holder removed it while we opened it: try again
            try:
                pid = lock.read_text().strip()[:20]
            except OSError:
                pid = "?"
            raise DVRInputError(
                f"{what}: another dvr-perception run (pid {pid or '?'}) is writing it "
                f"(lock file {lock}); wait for it or choose another name"
            ) from None
        if same:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)  # replaced between open and lock: try again


def _subfolders(final: Path, targets) -> list[Path]:
    """Create the subfolders of ``final`` that ``targets`` need; return those made, in order."""
    made = []
    for parent in sorted({t.parent for t in targets}, key=lambda p: len(p.parts)):
        missing = [p for p in (parent, *parent.parents) if p != final and final in p.parents]
        for p in reversed(missing):
            if not p.exists():
                p.mkdir()
                made.append(p)
    return made


@contextmanager
def file_lock(path) -> Iterator[Path]:
    """Hold ``.NAME.lock`` beside the output file ``path``: a second run is refused meanwhile.

    Examples
    --------
    >>> import tempfile
    >>> target = Path(tempfile.mkdtemp()) / "big.nhdr"
    >>> with file_lock(target) as lock:
    ...     lock.name
    '.big.nhdr.lock'
    >>> lock.exists()
    False
    """
    target = Path(path)
    lock = target.parent / f".{target.name}.lock"
    fd = _lock(target.parent, lock, f"output file {target}")
    try:
        yield lock
    finally:
        with _deferred_sigint():
            lock.unlink(missing_ok=True)
            os.close(fd)


def _publish(final: Path, staging: Path, remove=()) -> list[Path]:
    """Move every file staged in ``staging`` into ``final`` (:func:`commit`); return them."""
    mode = file_mode()
    moves = []
    for f in sorted(staging.rglob("*")):
        if f.is_file():
            os.chmod(f, mode)
            moves.append((f, final / f.relative_to(staging)))
    made = _subfolders(final, [b for _, b in moves])
    try:
        commit(moves, remove)
    except BaseException:
        for d in reversed(made):  # subfolders made for this commit, if still empty
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    return [b for _, b in moves]


@contextmanager
def output_folder(path) -> Iterator[StagedFolder]:
    """Write a multi-file output all at once: lock, stage, check, then move everything in.

    The folder is created if needed and must be writable (checked before the caller's work),
    a lock file (:data:`LOCK_NAME`) keeps a second run out, the caller writes into a hidden
    staging folder inside it, and when the block succeeds every staged file (those in staged
    subfolders too, into the same subfolders) is moved into the folder with Ctrl-C held back
    (:func:`commit`).  If the block fails or is interrupted, the
    staged files are removed, a folder this call created is removed again if empty, and the
    folder holds exactly what it held before, plus what :meth:`StagedFolder.publish` already
    moved in (a two-step output: the result first, its figures after).

    Yields
    ------
    StagedFolder
        ``.path`` is the staging folder to write into; ``.final`` the output folder.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "run"
    >>> with output_folder(out) as staged:
    ...     _ = (staged.path / "a.txt").write_text("a")
    >>> sorted(p.name for p in out.iterdir())
    ['a.txt']
    """
    final = Path(path)
    if final.exists() and not final.is_dir():
        raise DVRInputError(f"output folder {final}: exists and is not a folder")
    created = not final.exists()
    if created:
        try:
            final.mkdir(parents=True)
        except OSError as exc:
            raise DVRInputError(
                f"output folder {final}: cannot create it ({exc.strerror})"
            ) from None
    staging = None
    fd = None
    try:
        check_writable(final)
        fd = _lock(final)
        staging = Path(tempfile.mkdtemp(prefix=".dvr-perception.staging-", dir=final))
        yield StagedFolder(final, staging)
        _publish(final, staging)
    finally:
        with _deferred_sigint():
            if staging is not None:
                shutil.rmtree(staging, ignore_errors=True)
            if fd is not None:
                (final / LOCK_NAME).unlink(missing_ok=True)
                os.close(fd)
            if created:
                with contextlib.suppress(OSError):
                    final.rmdir()  # only if empty: a failed run leaves no folder behind


def _to_uint8_image(image) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise DVRInputError(
            f"write_png: image must have shape (height, width, 3 or 4), got {arr.shape}"
        )
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind not in "fb":
        raise DVRInputError(
            f"write_png: image must be uint8 or floating point in [0, 1], got dtype {arr.dtype}"
        )
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise DVRInputError("write_png: image contains NaN or infinite values")
    if arr.min() < -1e-6 or arr.max() > 1 + 1e-6:
        raise DVRInputError(
            f"write_png: float image values must lie in [0, 1], got range "
            f"[{arr.min():.4g}, {arr.max():.4g}]"
        )
    return np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path, image) -> Path:
    """Write an RGB or RGBA image as a PNG file (atomically).

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    image : array_like
        ``(height, width, 3)`` or ``(height, width, 4)`` array, either ``uint8`` or floating
        point in ``[0, 1]``.  Row 0 is the **top** of the picture.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "red.png"
    >>> _ = write_png(out, np.tile([1.0, 0.0, 0.0], (2, 3, 1)))
    >>> read_png(out).shape
    (2, 3, 3)
    """
    blob = png_bytes(_to_uint8_image(image))
    with atomic_path(path) as tmp:
        tmp.write_bytes(blob)
    return Path(path)


#: zlib level of the PNG encoder: 6 (zlib's default) compresses renderings about as well as 9
#: in a fraction of the time.
PNG_LEVEL = 6


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    body = kind + data
    return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)


def png_bytes(pixels: np.ndarray) -> bytes:
    r"""Encode ``(height, width, 3 or 4)`` uint8 pixels (row 0 at the top) as a PNG file.

    8 bits per channel, RGB or RGBA, no interlacing, filter type 0 (none) on every row: the
    PNG format in its plainest form, written with the standard library (``zlib``), so writing
    a picture needs no VTK import.

    Examples
    --------
    >>> blob = png_bytes(np.zeros((1, 2, 3), np.uint8))
    >>> blob[:8], blob[12:16], blob[-8:-4]
    (b'\x89PNG\r\n\x1a\n', b'IHDR', b'IEND')
    """
    h, w, c = pixels.shape
    rows = np.zeros((h, 1 + w * c), np.uint8)  # a leading 0 per row: filter type "none"
    rows[:, 1:] = np.ascontiguousarray(pixels, np.uint8).reshape(h, w * c)
    header = struct.pack(">IIBBBBB", w, h, 8, 6 if c == 4 else 2, 0, 0, 0)
    return b"".join((
        b"\x89PNG\r\n\x1a\n",
        _png_chunk(b"IHDR", header),
        _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_LEVEL)),
        _png_chunk(b"IEND", b""),
    ))  # fmt: skip


def read_png(path) -> np.ndarray:
    """Read a PNG file into a ``(height, width, channels)`` uint8 array, row 0 at the top.

    Parameters
    ----------
    path : str or os.PathLike
        PNG file to read.

    Returns
    -------
    numpy.ndarray
        The pixels, ``uint8``.
    """
    from dvr_perception import _vtk  # VTK on use: the core imports without it

    p = Path(path)
    if not p.is_file():
        raise DVRInputError(f"PNG file {p}: not found")
    reader = _vtk.vtkPNGReader()
    if not reader.CanReadFile(str(p)):
        raise DVRInputError(f"PNG file {p}: not a readable PNG image")
    reader.SetFileName(str(p))
    reader.Update()
    out = reader.GetOutput()
    w, h, _ = out.GetDimensions()
    scalars = _vtk.vtk_to_numpy(out.GetPointData().GetScalars())
    return np.ascontiguousarray(scalars.reshape(h, w, -1)[::-1]).astype(np.uint8, copy=False)


def json_ready(obj):
    """Convert ``obj`` into plain JSON types.

    NumPy scalars and arrays become Python numbers and lists, tuples become lists, paths become
    strings, and non-finite floats become ``None`` (JSON has no NaN).

    Examples
    --------
    >>> json_ready({"a": np.float32(0.5), "b": np.arange(2), "c": float("nan")})
    {'a': 0.5, 'b': [0, 1], 'c': None}
    """
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    raise DVRInputError(f"JSON output: cannot convert a {type(obj).__name__} value to JSON")


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON (atomically), converting NumPy types first.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    obj : object
        Anything :func:`json_ready` accepts.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    text = json.dumps(json_ready(obj), indent=2) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_npz(path, **arrays) -> Path:
    """Write arrays into an uncompressed ``.npz`` archive (atomically).

    Parameters
    ----------
    path : str or os.PathLike
        Output file; it is written exactly there (no ``.npz`` is appended).
    **arrays : array_like
        Named arrays.  Strings are stored as NumPy unicode arrays; object arrays are refused
        because reading them back would need ``allow_pickle``.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    converted = {}
    for name, value in arrays.items():
        arr = np.asarray(value)
        if arr.dtype.kind == "O":
            raise DVRInputError(
                f"write_npz: array {name!r} has dtype object; expected numbers or strings"
            )
        converted[name] = arr
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **converted)
    return Path(path)
