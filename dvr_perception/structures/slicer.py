r"""3D Slicer segmentations (``.seg.nrrd``) as label structures.

A Slicer segmentation is a NRRD label volume whose header carries one group of ``key:=value``
fields per segment ``N`` (``SegmentN_ID``, ``SegmentN_Name``, ``SegmentN_Color`` as ``"r g b"``
in [0, 1], ``SegmentN_LabelValue``, ``SegmentN_Layer``, ``SegmentN_Extent``, ``SegmentN_Tags``,
...) and ``Segmentation_*`` fields for the whole file.  :func:`spec_from_segmentation` turns
every segment into a label structure (its name, colour and label value) and names the file as
the spec's label volume; :func:`segmentation_labels` places the segmentation's voxels into a
volume's grid.

Default importance
    Segments are ranked by their voxel count: the smallest segment gets importance 0.85, the
    largest 0.15, the others evenly in between (equal counts share a value; one segment gets
    0.5).  Segmentations nest: the large segments (body, skin, an organ) enclose the small ones
    (a tumour, vessels) that are usually what the segmentation was made for, so the enclosing
    ones are shown faint and the enclosed ones strong -- the same range and direction as
    :func:`~dvr_perception.structures.propose.propose_structures` (inner structures more
    important).  Write the spec with ``--save-spec`` and edit it to change them.

Geometry
    The segmentation must share the volume's voxel spacing.  Slicer may store a segmentation
    cropped to the segments' extent: its ``space origin`` then lies on the volume's grid at an
    index offset, and the voxels are placed there (``Segmentation_ReferenceImageExtentOffset``
    is not needed: the origin says the same in physical space).  Both grids are assumed to have
    the same axis directions (both are loaded in canonical LPS order, see
    :mod:`dvr_perception.volume.orient`).
    Segment voxels outside the volume, a spacing that differs or an origin off the volume's grid
    give one :class:`~dvr_perception.errors.DVRInputError` naming the file and what differs.

Names
    A segment's name is kept when it is a valid structure name
    (:func:`~dvr_perception.structures.spec.name_problem`: at most
    :data:`~dvr_perception.structures.spec.MAX_NAME_LENGTH` printable characters).  Otherwise
    it is sanitised with one :class:`~dvr_perception.errors.DVRWarning` naming the file and the
    field: control and other non-printable characters are escaped (``\x1b``) and a long name
    is cut (ending in ``…``).  Unlike a spec JSON, whose author fixes a refused name in a text
    editor, a segmentation is written by Slicer (names often come from its terminology
    lists) into a file that mixes a text header with binary data, and segments are matched by
    their label value, not by name: refusing the file would leave a valid segmentation
    unusable for a display label.  A spec written with ``--save-spec`` holds the sanitised
    names.  Two names that become equal are refused as duplicates.

Limits
    Only single-layer segmentations (3-D, segments do not overlap) are read; a multi-layer file
    (4-D, ``kinds: list domain domain domain``, written by Slicer when segments overlap) is
    refused with one error that says how to make a single-layer one.  At most
    :data:`~dvr_perception.structures.spec.MAX_STRUCTURES` segments.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.spec import (
    MAX_NAME_LENGTH,
    MAX_STRUCTURES,
    Structure,
    StructureSpec,
    name_problem,
    printable,
)

__all__ = [
    "SEGMENTATION_SUFFIXES",
    "default_importances",
    "is_segmentation",
    "read_segments",
    "segmentation_labels",
    "spec_from_segmentation",
]

#: File name endings read as a segmentation (a ``.nrrd``/``.nhdr`` also when its header has
#: ``SegmentN_`` fields).
SEGMENTATION_SUFFIXES = (".seg.nrrd", ".seg.nhdr")
_NRRD = (".nrrd", ".nhdr")
_SEGMENT_KEY = re.compile(r"^Segment(\d{1,6})_(\w+)$")
_LABEL_MAX = 2**31 - 1
_IMPORTANCE_RANGE = (0.15, 0.85)
_OTHER_VOLUME = (
    "the segmentation was made on another volume, or the volume was read without its origin "
    "(e.g. a DICOM series)"
)


def _header(path: Path) -> tuple[dict[str, str], dict[str, str]]:
    from dvr_perception.volume._nrrd import nrrd_header

    if not path.is_file():
        raise DVRInputError(f"{path}: segmentation file not found")
    keyvalues: dict[str, str] = {}
    fields, _ = nrrd_header(path, keyvalues)
    return fields, keyvalues


def is_segmentation(path) -> bool:
    """Tell whether ``path`` names a Slicer segmentation rather than a spec JSON file.

    True for ``*.seg.nrrd``/``*.seg.nhdr`` and for a ``.nrrd``/``.nhdr`` file whose header has
    ``SegmentN_`` fields.

    Examples
    --------
    >>> is_segmentation("organs.seg.nrrd"), is_segmentation("spec.json")
    (True, False)
    """
    path = Path(path)
    name = path.name.lower()
    if name.endswith(SEGMENTATION_SUFFIXES):
        return True
    if not name.endswith(_NRRD) or not path.is_file():
        return False
    try:
        _, keyvalues = _header(path)
    except DVRInputError:
        return False
    return any(_SEGMENT_KEY.match(k) for k in keyvalues)


def _fail(path: Path, field: str, message: str):
    raise DVRInputError(f"{path}: segmentation field {field!r}: {message}")


def _label_value(path: Path, key: str, text: str) -> int:
    tok = text.strip()
    if not re.fullmatch(r"[+-]?\d{1,12}", tok):
        _fail(path, key, f"expected an integer label value, got {tok[:40]!r}")
    value = int(tok)
    if not 1 <= value <= _LABEL_MAX:
        _fail(path, key, f"expected a label value in 1..{_LABEL_MAX}, got {value}")
    return value


def _color(path: Path, key: str, text: str) -> tuple[float, float, float]:
    parts = text.split()
    try:
        rgb = tuple(float(p) for p in parts if len(p) <= 40)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or len(parts) != 3:
        _fail(path, key, f"expected three numbers 'r g b' in [0, 1], got {text.strip()[:60]!r}")
    if not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in rgb):
        _fail(path, key, f"colour components must be in [0, 1], got {text.strip()[:60]!r}")
    return rgb  # type: ignore[return-value]


def read_segments(path, *, warn: bool = True) -> list[dict]:
    """Read and check the segment fields of a ``.seg.nrrd`` header (no voxel data is read).

    Parameters
    ----------
    path : str or os.PathLike
        The segmentation file.
    warn : bool
        Emit a :class:`~dvr_perception.errors.DVRWarning` per sanitised name (see Names in the
        module docstring); ``False`` where the file was read before.

    Returns
    -------
    list of dict
        One ``{"index", "id", "name", "color", "label"}`` per segment, in segment order.

    Raises
    ------
    DVRInputError
        Naming the file and the field: not a NRRD, a multi-layer (4-D) file, a non-integer
        voxel type, no segments, more than ``MAX_STRUCTURES`` segments, a missing or bad
        ``LabelValue``, a colour out of [0, 1], a ``Layer`` other than 0, duplicate label
        values or names, or no voxel data (Slicer's single-voxel file of empty segments).
    """
    path = Path(path)
    fields, keyvalues = _header(path)
    dim = fields.get("dimension", "").strip()
    if dim == "4":
        raise DVRInputError(
            f"{path}: a multi-layer segmentation (4-D, overlapping segments) is not supported; "
            "make the segments not overlap (e.g. Segment Editor with overwrite 'All segments') "
            "and save it again, or export it to a labelmap volume"
        )
    if dim != "3":
        _fail(path, "dimension", f"expected 3, got {dim[:20]!r}")
    from dvr_perception.volume._nrrd import NRRD_TYPES

    code = NRRD_TYPES.get(" ".join(fields.get("type", "").lower().split()), "")
    if not code or code[0] not in "iu":
        _fail(
            path,
            "type",
            f"a segmentation holds integer label values, got {fields.get('type', '')[:40]!r}",
        )
    if fields.get("sizes", "").split() == ["1", "1", "1"]:  # how Slicer saves empty segments
        raise DVRInputError(
            f"{path}: the segmentation holds no voxel data (its segments are empty)"
        )
    groups: dict[int, dict[str, str]] = {}
    for key, value in keyvalues.items():
        m = _SEGMENT_KEY.match(key)
        if m:
            groups.setdefault(int(m.group(1)), {})[m.group(2)] = value
    if not groups:
        raise DVRInputError(
            f"{path}: no 'SegmentN_' header fields: not a 3D Slicer segmentation (.seg.nrrd)"
        )
    if len(groups) > MAX_STRUCTURES:
        raise DVRInputError(
            f"{path}: {len(groups)} segments, more than the {MAX_STRUCTURES} structures a spec "
            "may hold; remove or merge segments in Slicer, or write a spec JSON with the "
            "segments you need"
        )
    segments: list[dict] = []
    seen_label: dict[int, str] = {}
    seen_name: dict[str, str] = {}
    for index in sorted(groups):
        g = groups[index]
        pre = f"Segment{index}_"
        if "LabelValue" not in g:
            _fail(
                path,
                pre + "LabelValue",
                "is missing (files of Slicer before 4.11 store one segment per layer; open "
                "and save the segmentation in a current Slicer)",
            )
        label = _label_value(path, pre + "LabelValue", g["LabelValue"])
        layer = g.get("Layer", "0").strip()
        if layer != "0":
            _fail(path, pre + "Layer", f"only single-layer segmentations are read, got {layer!r}")
        if "Color" not in g:
            _fail(path, pre + "Color", "is missing; expected 'r g b' in [0, 1]")
        color = _color(path, pre + "Color", g["Color"])
        seg_id = g.get("ID", "").strip()
        raw = g.get("Name", "").strip() or seg_id or f"Segment_{index}"
        name = printable(raw, MAX_NAME_LENGTH)
        if name != raw and warn:  # sanitised, not refused: see the module docstring (Names)
            warnings.warn(
                f"{path}: {pre}Name {name_problem(raw)}; shown as {name!r}",
                DVRWarning,
                stacklevel=2,
            )
        if label in seen_label:
            _fail(path, pre + "LabelValue", f"{label} duplicates {seen_label[label]}")
        if name in seen_name:
            _fail(path, pre + "Name", f"{name!r} duplicates {seen_name[name]}")
        seen_label[label] = pre + "LabelValue"
        seen_name[name] = pre + "Name"
        segments.append(
            {"index": index, "id": seg_id, "name": name, "color": color, "label": label}
        )
    return segments


def default_importances(counts) -> list[float]:
    """Return the importance of each segment from its voxel count (the module's default rule).

    The smallest segment gets 0.85, the largest 0.15, evenly by rank in between; equal counts
    share the mean of their ranks' values; a single segment gets 0.5.

    Examples
    --------
    >>> default_importances([1000, 10, 200])
    [0.15, 0.85, 0.5]
    >>> default_importances([5])
    [0.5]
    """
    counts = [int(c) for c in counts]
    k = len(counts)
    if k == 1:
        return [0.5]
    lo, hi = _IMPORTANCE_RANGE
    steps = np.linspace(hi, lo, k)  # by rank, smallest first
    order = sorted(range(k), key=lambda i: counts[i])
    value = [0.0] * k
    pos = 0
    while pos < k:
        end = pos
        while end + 1 < k and counts[order[end + 1]] == counts[order[pos]]:
            end += 1
        shared = float(np.mean(steps[pos : end + 1]))
        for r in range(pos, end + 1):
            value[order[r]] = round(shared, 4)
        pos = end + 1
    return value


def _counts(data: np.ndarray, labels: list[int]) -> list[int]:
    """Voxels per label value (a histogram in slabs for 8- and 16-bit data)."""
    if data.dtype.kind in "ui" and data.dtype.itemsize <= 2:
        from dvr_perception.structures._counts import int_histogram

        lo, hi = int(data.min()), int(data.max())
        hist = int_histogram(data, lo, hi - lo + 1)
        return [int(hist[v - lo]) if lo <= v <= hi else 0 for v in labels]
    return [int(np.count_nonzero(data == v)) for v in labels]


def spec_from_segmentation(path, volume=None, *, importance=None) -> StructureSpec:
    """Build a label-structure spec from a 3D Slicer segmentation file.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.seg.nrrd`` (or ``.seg.nhdr``) file; it becomes the spec's ``labels_file``.
    volume : Volume, optional
        When given, the segmentation's geometry is checked against it now (as
        :func:`segmentation_labels` does) instead of when the labels are attached.
    importance : float, optional
        One importance for every segment; default: by voxel count (see the module docstring).

    Returns
    -------
    StructureSpec
        One label structure per segment, in the file's segment order, with the segment's name,
        colour and label value.

    Raises
    ------
    DVRInputError
        Naming the file and the field (see :func:`read_segments`), or the geometry that
        differs from ``volume``'s.

    Examples
    --------
    >>> import os, tempfile
    >>> from dvr_perception.structures.slicer import write_segmentation_for_doc
    >>> path = write_segmentation_for_doc(os.path.join(tempfile.mkdtemp(), "demo.seg.nrrd"))
    >>> spec = spec_from_segmentation(path)
    >>> [(s.name, s.label, s.importance) for s in spec.structures]
    [('shell', 1, 0.15), ('core', 2, 0.85)]
    """
    from dvr_perception.volume.io import load_volume

    path = Path(path)
    segments = read_segments(path)
    if importance is not None:
        if not (isinstance(importance, (int, float)) and 0 < importance <= 1):
            raise DVRInputError(f"importance must be a number in (0, 1], got {importance!r}")
        importances = [float(importance)] * len(segments)
    else:
        seg = load_volume(path)
        importances = default_importances(_counts(seg.data, [s["label"] for s in segments]))
    if volume is not None:
        segmentation_labels(path, volume)
    structures = tuple(
        Structure(name=s["name"], importance=imp, colour=s["color"], label=s["label"])
        for s, imp in zip(segments, importances, strict=True)
    )
    return StructureSpec(structures=structures, labels_file=str(path.resolve()))


def _directions(fields: dict[str, str], path: Path) -> np.ndarray:
    from dvr_perception.volume._nrrd import nrrd_vector

    text = fields.get("space directions")
    if text is None:
        spacing = fields.get("spacings", "1 1 1").split()
        try:
            return np.diag([abs(float(s)) if s.lower() != "nan" else 1.0 for s in spacing[:3]])
        except ValueError:
            _fail(path, "spacings", "expected 3 numbers")
    vecs = re.findall(r"\(([^)]*)\)", text[:2000])
    rows = [nrrd_vector(v, path, "space directions") for v in vecs]
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        _fail(path, "space directions", "expected 3 vectors")
    return np.array(rows, float)


def segmentation_labels(path, volume) -> np.ndarray:
    """Return the segmentation's label values in ``volume``'s grid (shape ``volume.data.shape``).

    A segmentation cropped to a smaller extent is placed at the index its ``space origin``
    gives in the volume's grid; voxels outside it are 0.

    Raises
    ------
    DVRInputError
        Naming the file and what differs: the spacing, an origin off the volume's grid, or
        segment voxels outside the volume; also any error of :func:`read_segments` and
        :func:`~dvr_perception.volume.io.load_volume`.
    """
    from dvr_perception.volume.io import load_volume

    path = Path(path)
    read_segments(path, warn=False)  # the header checks, before any voxel is read
    fields, _ = _header(path)
    seg = load_volume(path)
    spacing = np.array(seg.spacing, float)
    vspacing = np.array(volume.spacing, float)
    if not np.allclose(spacing, vspacing, rtol=1e-4, atol=1e-9):
        raise DVRInputError(
            f"{path}: the segmentation's voxel spacing {tuple(round(float(s), 6) for s in spacing)}"
            f" differs from the volume's {tuple(round(float(s), 6) for s in vspacing)}; resample "
            "the segmentation to the volume in Slicer (Segmentations: export to the volume's "
            "geometry)"
        )
    seg_dims = np.array(seg.dims)
    vol_dims = np.array(volume.dims)
    _directions(fields, path)  # the header's vectors are well formed
    # both grids come from the loaders in canonical LPS order (flips and permutations applied
    # to the data), so one direction matrix maps the origin difference to an index offset
    if not np.allclose(seg.direction, volume.direction, atol=1e-4):
        _fail(path, "space directions", "the axis directions differ from the volume's")
    delta = np.array(seg.origin, float) - np.array(volume.origin, float)
    offset = (np.asarray(seg.direction).T @ delta) / spacing
    if not np.all(np.abs(offset) < 2**31):  # far away (or not finite): certainly outside
        offset = np.full(3, 2.0**31)
    index = np.round(offset)
    if not np.all(np.abs(offset - index) < 1e-3):
        raise DVRInputError(
            f"{path}: the segmentation's origin {tuple(round(float(o), 6) for o in seg.origin)} "
            f"is not on the volume's voxel grid (origin "
            f"{tuple(round(float(o), 6) for o in volume.origin)}, index offset "
            f"{tuple(round(float(o), 3) for o in offset)}); {_OTHER_VOLUME}"
        )
    start = index.astype(np.int64)
    if np.array_equal(start, [0, 0, 0]) and np.array_equal(seg_dims, vol_dims):
        return seg.data
    lo = np.maximum(start, 0)
    hi = np.minimum(start + seg_dims, vol_dims)
    out = np.zeros(volume.data.shape, seg.data.dtype)
    if np.any(hi <= lo):
        inside = None
    else:
        inside = tuple(slice(int(a), int(b)) for a, b in zip(lo - start, hi - start, strict=True))
    kept = 0 if inside is None else int(np.count_nonzero(seg.data[inside[::-1]]))
    if kept != int(np.count_nonzero(seg.data)):
        raise DVRInputError(
            f"{path}: segment voxels lie outside the volume: the segmentation (dims "
            f"{tuple(int(d) for d in seg_dims)}) starts at index {tuple(int(s) for s in start)} "
            f"of the volume (dims {tuple(int(d) for d in vol_dims)}); {_OTHER_VOLUME}"
        )
    if inside is not None:
        target = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
        out[target[::-1]] = seg.data[inside[::-1]]
    return out


def write_segmentation(path, labels, segments, *, spacing=(1.0, 1.0, 1.0), origin=(0, 0, 0),
                       encoding: str = "gzip", extra: dict | None = None) -> Path:  # fmt: skip
    """Write a single-layer Slicer-style ``.seg.nrrd`` (for tests, examples and round trips).

    Parameters
    ----------
    path : str or os.PathLike
        Target file.
    labels : numpy.ndarray
        Integer label values, indexed ``[z, y, x]``.
    segments : list of dict
        ``{"name", "color", "label"}`` per segment (optional ``"id"``).
    spacing, origin : sequence of float
        Voxel spacing and the position of the first voxel (axis-aligned, LPS).
    encoding : {"gzip", "raw"}
        Data encoding.
    extra : dict, optional
        ``key:=value`` fields to add or replace; a ``None`` value leaves the field out (e.g. to
        write a broken file in a test).

    Returns
    -------
    pathlib.Path
    """
    import gzip

    from dvr_perception.volume._nrrd import NRRD_NAMES

    labels = np.ascontiguousarray(labels)
    code = labels.dtype.str[1:]
    if code not in NRRD_NAMES:
        raise DVRInputError(f"{path}: cannot store dtype {labels.dtype}")
    z, y, x = labels.shape
    directions = " ".join(
        "(" + ",".join(repr(float(s)) if i == j else "0" for j in range(3)) + ")"
        for i, s in enumerate(spacing)
    )
    lines = [
        "NRRD0004",
        f"type: {NRRD_NAMES[code]}",
        "dimension: 3",
        "space: left-posterior-superior",
        f"sizes: {x} {y} {z}",
        f"space directions: {directions}",
        "kinds: domain domain domain",
        "endian: little",
        f"encoding: {encoding}",
        "space origin: (" + ",".join(repr(float(o)) for o in origin) + ")",
        "Segmentation_ContainedRepresentationNames:=Binary labelmap|",
        "Segmentation_MasterRepresentation:=Binary labelmap",
        "Segmentation_ReferenceImageExtentOffset:=0 0 0",
    ]
    kv: dict[str, object] = {}
    for i, s in enumerate(segments):
        r, g, b = s["color"]
        kv[f"Segment{i}_Color"] = f"{r:g} {g:g} {b:g}"
        kv[f"Segment{i}_ColorAutoGenerated"] = 0
        kv[f"Segment{i}_Extent"] = f"0 {x - 1} 0 {y - 1} 0 {z - 1}"
        kv[f"Segment{i}_ID"] = s.get("id", f"Segment_{i + 1}")
        kv[f"Segment{i}_LabelValue"] = s["label"]
        kv[f"Segment{i}_Layer"] = 0
        kv[f"Segment{i}_Name"] = s["name"]
        kv[f"Segment{i}_NameAutoGenerated"] = 0
        kv[f"Segment{i}_Tags"] = "|"
    kv.update(extra or {})
    lines += [f"{k}:={v}" for k, v in kv.items() if v is not None]
    payload = labels.astype(labels.dtype.newbyteorder("<")).tobytes()
    if encoding == "gzip":
        payload = gzip.compress(payload, compresslevel=1)
    elif encoding != "raw":
        raise DVRInputError(f"{path}: encoding must be gzip or raw, got {encoding!r}")
    path = Path(path)
    path.write_bytes(("\n".join(lines) + "\n\n").encode("utf-8") + payload)
    return path


def write_segmentation_for_doc(path) -> Path:
    """Write a 6³ two-segment segmentation (a shell around a core), for the examples."""
    labels = np.zeros((6, 6, 6), np.uint8)
    labels[1:5, 1:5, 1:5] = 1
    labels[2:4, 2:4, 2:4] = 2
    segments = [
        {"name": "shell", "color": (0.9, 0.8, 0.7), "label": 1},
        {"name": "core", "color": (1.0, 0.2, 0.1), "label": 2},
    ]
    return write_segmentation(path, labels, segments)
