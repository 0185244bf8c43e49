"""Presets paired with a volume by the content of its data, not by its file name.

A preset is a spec JSON in the repository's ``state_files/`` folder.  It pairs with a volume
only when it records that volume's data checksum (the ``"data"`` field, see
:func:`data_fingerprint`) or when the user names it (``--preset NAME``).  The same data saved in
another format or folder still pairs; another file with a shared volume's name does not.

:func:`choose_spec` is the one loader the command line, the web app and the ParaView batch
scripts use: a named preset, else the preset whose checksum matches, else a proposal
(:func:`~dvr_perception.structures.propose.propose_structures`), with a one-line reason.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "SpecChoice",
    "choose_spec",
    "data_checksum",
    "data_fingerprint",
    "load_preset",
    "match_preset",
    "preset_names",
    "presets_dir",
]

#: Field of a preset JSON that records the data it belongs to.
DATA_FIELD = "data"
_SLAB_BYTES = 64 * 2**20


def presets_dir() -> Path:
    """Return the repository's ``state_files`` folder (the presets of the shared volumes)."""
    return Path(__file__).resolve().parents[2] / "state_files"


def data_checksum(data) -> str:
    """SHA-256 (hex) of a voxel array: its dtype name, shape and C-ordered little-endian bytes.

    Independent of the file format, folder and byte order the array was read from; hashed in
    slabs, so a non-contiguous array is not copied whole.

    Examples
    --------
    >>> a = np.arange(8, dtype="<u2").reshape(2, 2, 2)
    >>> data_checksum(a) == hashlib.sha256(b"uint16:(2, 2, 2):" + a.tobytes()).hexdigest()
    True
    >>> same = data_checksum(a)
    >>> data_checksum(a.astype(">u2")) == same, data_checksum(a[:, :, ::-1]) == same
    (True, False)
    >>> data_checksum(a.astype(np.uint8)) == data_checksum(a)
    False
    """
    a = np.asarray(data)
    dtype = a.dtype.newbyteorder("<")
    h = hashlib.sha256(f"{np.dtype(dtype).name}:{tuple(a.shape)}:".encode())
    if a.ndim == 0 or a.size == 0:
        h.update(np.ascontiguousarray(a, dtype=dtype).tobytes())
        return h.hexdigest()
    per = max(1, _SLAB_BYTES // max(1, a[0].nbytes))
    for i in range(0, a.shape[0], per):
        h.update(memoryview(np.ascontiguousarray(a[i : i + per], dtype=dtype)).cast("B"))
    return h.hexdigest()


def data_fingerprint(volume) -> dict:
    """Return the ``"data"`` field a preset records for ``volume``: dtype, dims, sha256.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> fp = data_fingerprint(Volume(np.zeros((2, 3, 4), np.uint8)))
    >>> fp["dtype"], fp["dims"], len(fp["sha256"])
    ('uint8', [4, 3, 2], 64)
    """
    data = volume.data
    return {
        "dtype": np.dtype(data.dtype).name,
        "dims": [int(d) for d in data.shape[::-1]],
        "sha256": data_checksum(data),
    }


def preset_names(folder=None) -> list[str]:
    """Names of the presets in ``folder`` (default :func:`presets_dir`), sorted."""
    folder = presets_dir() if folder is None else Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.stem for p in folder.glob("*.json") if p.is_file())


def load_preset(name: str, folder=None):
    """Return ``(spec, path)`` of the preset ``name`` (``--preset NAME``).

    Raises
    ------
    DVRInputError
        Naming the known presets when there is none called ``name``.
    """
    from dvr_perception.structures.io import load_spec

    folder = presets_dir() if folder is None else Path(folder)
    names = preset_names(folder)
    text = str(name)
    if text not in names:
        known = ", ".join(names) if names else "none"
        raise DVRInputError(f"--preset {text[:40]!r}: no such preset (known: {known})")
    path = folder / f"{text}.json"
    return load_spec(path), path


def _recorded(path: Path):
    """Return the ``"data"`` field of a preset file, or ``None`` (unreadable files are skipped)."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    rec = d.get(DATA_FIELD) if isinstance(d, dict) else None
    if not isinstance(rec, dict) or not isinstance(rec.get("sha256"), str):
        return None
    return rec


def match_preset(volume, folder=None):
    """Return ``(name, path)`` of the preset recording ``volume``'s data checksum, or ``None``.

    Only presets of the same dtype and dims are candidates, so the checksum is computed at
    most once and only when one could match.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> match_preset(Volume(np.zeros((2, 2, 2), np.uint8))) is None
    True
    """
    folder = presets_dir() if folder is None else Path(folder)
    data = volume.data
    dtype, dims = np.dtype(data.dtype).name, [int(d) for d in data.shape[::-1]]
    candidates = []
    for name in preset_names(folder):
        path = folder / f"{name}.json"
        rec = _recorded(path)
        if rec is not None and rec.get("dtype") == dtype and rec.get("dims") == dims:
            candidates.append((name, path, rec["sha256"]))
    if not candidates:
        return None
    checksum = data_checksum(data)
    for name, path, recorded in candidates:
        if recorded == checksum:
            return name, path
    return None


@dataclass(frozen=True)
class SpecChoice:
    """The spec chosen for a volume, where it came from and why (:func:`choose_spec`)."""

    spec: object
    source: str
    line: str


def choose_spec(
    volume, *, preset=None, n_structures=None, propose: bool = False, folder=None
) -> SpecChoice:
    """Choose the spec for ``volume``: the preset named, one matching its data, or a proposal.

    Parameters
    ----------
    volume : Volume
        The volume as read from its file (before any re-orientation).
    preset : str, optional
        A preset name (``--preset NAME``); used whatever the data.
    n_structures : int, optional
        Number of proposed structures (``--classes N``); also skips the checksum pairing.
    propose : bool
        Propose (with the number of structures the data choose) even when a preset matches
        (``--classes auto``).
    folder : path, optional
        The presets' folder (default :func:`presets_dir`).

    Returns
    -------
    SpecChoice
        ``source`` is the preset file or ``"proposed"``; ``line`` says which spec and why,
        e.g. ``structures: preset 'cthead' (data checksum matches)``.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> data = np.repeat(np.array([0, 0, 100, 200], np.uint8), 8).reshape(2, 4, 4)
    >>> choose_spec(Volume(data)).line
    'structures proposed from the data (no preset matches this file)'
    """
    from dvr_perception.structures.propose import describe_proposal, propose_structures

    if preset is not None:
        spec, path = load_preset(preset, folder)
        return SpecChoice(spec, str(path), f"structures: preset {preset!r} (given with --preset)")
    if n_structures is None and not propose:
        found = match_preset(volume, folder)
        if found is not None:
            from dvr_perception.structures.io import load_spec

            name, path = found
            line = f"structures: preset {name!r} (data checksum matches)"
            return SpecChoice(load_spec(path), str(path), line)
        why = "no preset matches this file"
    elif n_structures is None:
        why = "asked with --classes auto"
    else:
        why = f"{n_structures} requested with --classes"
    spec = propose_structures(volume, n_structures=n_structures)
    return SpecChoice(spec, "proposed", f"{describe_proposal(spec)} ({why})")
