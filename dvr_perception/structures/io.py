"""Read, validate and write structure-spec JSON files (format version 1).

The format::

    {"version": 1,
     "background": [r, g, b],                              # optional, default black
     "structures": [
        {"name": "bone", "range": [lo, hi],                 # or "label": int
         "importance": 0.8, "colour": [r, g, b],  # or "color"
         "lighting": {"ambient", "diffuse", "specular", "specular_power"},   # optional
         "expected_opacity": 0.8, "opacity": 0.5,            # optional
         "edge": 0.1},                                      # optional, in [0, 0.5]
        ...],
     "rendering": {"shade", "sample_distance", "opacity_unit_distance",
                   "light_direction", "light_intensity"},   # optional
     "view": [azimuth, elevation, zoom],                    # optional
     "labels": "path/to/label_volume",                      # optional, relative to the file
     "data": {"dtype", "dims", "sha256"}}                   # optional: the data a preset
                                                            # belongs to (structures.presets)

Every violation raises one :class:`~dvr_perception.errors.DVRInputError` naming the field path,
e.g. ``spec.json: structures[2].importance must be in (0, 1], got 1.5``; unknown keys give one
:class:`~dvr_perception.errors.DVRWarning`.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
import warnings
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures._counts import int_histogram
from dvr_perception.structures.spec import StructureSpec, parse_spec_dict

__all__ = [
    "attach_labels",
    "check_spec_for_volume",
    "load_spec",
    "save_spec",
    "spec_from_dict",
    "spec_to_dict",
]

#: Largest spec file read (bytes).
MAX_SPEC_BYTES = 16 * 2**20


def spec_from_dict(d, *, source: str = "spec") -> StructureSpec:
    """Build a validated :class:`StructureSpec` from a parsed JSON object.

    Parameters
    ----------
    d : dict
        The parsed JSON (see the module docstring for the format).
    source : str
        Name used at the start of every error message (usually the file name).

    Returns
    -------
    StructureSpec

    Examples
    --------
    >>> spec = spec_from_dict({"version": 1, "structures": [
    ...     {"name": "skin", "range": [200, 650], "importance": 0.3, "colour": [1, .8, .7]}]})
    >>> spec.structures[0].range
    (200.0, 650.0)
    """
    spec, unknown = parse_spec_dict(_without_data_field(d), source)
    if unknown:
        warnings.warn(
            f"{source}: ignoring unknown field(s) {', '.join(unknown)}", DVRWarning, stacklevel=2
        )
    return spec


def _without_data_field(d):
    """``d`` without a preset's ``"data"`` record (read by :mod:`~.presets`, not the spec)."""
    if isinstance(d, dict) and isinstance(d.get("data"), dict):
        return {k: v for k, v in d.items() if k != "data"}
    return d


def _lighting_dict(light) -> dict:
    return {
        "ambient": light.ambient,
        "diffuse": light.diffuse,
        "specular": light.specular,
        "specular_power": light.specular_power,
    }


def spec_to_dict(spec: StructureSpec) -> dict:
    """JSON-ready dictionary of ``spec``; optional fields that are unset are omitted.

    Examples
    --------
    >>> d = {"version": 1, "structures": [
    ...     {"name": "a", "label": 3, "importance": 1.0, "colour": [1, 0, 0]}], "labels": "l.nhdr"}
    >>> spec_to_dict(spec_from_dict(d))["structures"][0]["lighting"]["specular_power"]
    16.0
    """
    structures = []
    for s in spec.structures:
        e: dict = {"name": s.name}
        if s.range is not None:
            e["range"] = [float(s.range[0]), float(s.range[1])]
        else:
            e["label"] = int(s.label)
        e["importance"] = float(s.importance)
        e["colour"] = [float(c) for c in s.colour]
        e["edge"] = float(s.edge)
        e["lighting"] = _lighting_dict(s.lighting)
        if s.opacity is not None:
            e["opacity"] = float(s.opacity)
        if s.expected_opacity is not None:
            e["expected_opacity"] = float(s.expected_opacity)
        structures.append(e)
    r = spec.rendering
    rendering: dict = {"shade": bool(r.shade)}
    if r.sample_distance is not None:
        rendering["sample_distance"] = float(r.sample_distance)
    if r.opacity_unit_distance is not None:
        rendering["opacity_unit_distance"] = float(r.opacity_unit_distance)
    rendering["light_direction"] = [float(c) for c in r.light_direction]
    rendering["light_intensity"] = float(r.light_intensity)
    out: dict = {
        "version": int(spec.version),
        "background": [float(c) for c in spec.background],
        "structures": structures,
        "rendering": rendering,
    }
    if spec.view is not None:
        out["view"] = [float(v) for v in spec.view]
    if spec.labels_file is not None:
        out["labels"] = str(spec.labels_file)
    return out


def loads_json(text: str, name: str):
    """Parse JSON ``text``, or raise one :class:`DVRInputError` naming ``name`` and the place.

    Examples
    --------
    >>> loads_json('{"a": [1, 2]}', "spec.json")
    {'a': [1, 2]}
    >>> try:
    ...     loads_json('{"a": }', "s.json")
    ... except ValueError as exc:
    ...     print(exc)
    s.json: not valid JSON at line 1, column 7: Expecting value
    """
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DVRInputError(
            f"{name}: not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except RecursionError:
        raise DVRInputError(f"{name}: JSON nested too deeply") from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise DVRInputError(f"{name}: not valid JSON ({str(exc)[:80]})") from None


def load_spec(path) -> StructureSpec:
    """Read and validate a spec JSON file.

    A relative ``labels`` path is resolved against the directory of the spec file, and the
    label file must exist.

    A 3D Slicer segmentation (``*.seg.nrrd``, or a NRRD with ``SegmentN_`` header fields) is
    read as one label structure per segment, with the file as the label volume
    (:func:`dvr_perception.structures.slicer.spec_from_segmentation`).

    Parameters
    ----------
    path : str or os.PathLike
        The JSON file, or a Slicer segmentation.

    Returns
    -------
    StructureSpec
    """
    path = Path(path)
    name = path.name
    from dvr_perception.structures.slicer import is_segmentation, spec_from_segmentation

    if is_segmentation(path):
        return spec_from_segmentation(path)
    try:
        st = path.stat()
        if stat.S_ISREG(st.st_mode) and st.st_size > MAX_SPEC_BYTES:
            raise DVRInputError(
                f"{path}: the spec file has {st.st_size} bytes, more than the {MAX_SPEC_BYTES} "
                "allowed"
            )
        if not stat.S_ISREG(st.st_mode) and not stat.S_ISDIR(st.st_mode):
            raise DVRInputError(f"{path}: expected a spec JSON file, got a device or pipe")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DVRInputError(f"{path}: spec file not found") from None
    except IsADirectoryError:
        raise DVRInputError(f"{path}: expected a spec JSON file, got a directory") from None
    except UnicodeDecodeError as exc:
        raise DVRInputError(f"{name}: not UTF-8 text ({exc.reason})") from None
    except OSError as exc:
        raise DVRInputError(f"{path}: cannot read spec file ({exc.strerror})") from None
    d = loads_json(text, name)
    spec, unknown = parse_spec_dict(_without_data_field(d), name)
    if unknown:
        warnings.warn(
            f"{name}: ignoring unknown field(s) {', '.join(unknown)}", DVRWarning, stacklevel=2
        )
    if spec.labels_file is not None:
        labels = Path(spec.labels_file)
        if not labels.is_absolute():
            labels = (path.parent / labels).resolve()
        if not labels.exists():
            raise DVRInputError(f"{name}: labels file {spec.labels_file!r} not found ({labels})")
        from dataclasses import replace

        spec = replace(spec, labels_file=str(labels))
    return spec


def _dumps(value, indent: str = "") -> str:
    """Indented JSON; lists of plain values and small flat objects are kept on one line."""
    inner = indent + "  "
    flat = isinstance(value, dict) and all(not isinstance(v, (dict, list)) for v in value.values())
    if flat and len(value) <= 4:
        return json.dumps(value, ensure_ascii=False, allow_nan=False)
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k)}: {_dumps(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + ",\n".join(inner + _dumps(v, inner) for v in value) + "\n" + indent + "]"
    return json.dumps(value, ensure_ascii=False, allow_nan=False)


def save_spec(spec: StructureSpec, path, *, relative_to=None) -> None:
    """Write ``spec`` as JSON, atomically (temporary file in the same folder, then rename).

    A ``labels_file`` is written relative to the folder of ``path`` (or to the folder
    ``relative_to``, where the file will be moved to) when possible.

    Examples
    --------
    >>> import tempfile, os
    >>> spec = spec_from_dict({"version": 1, "structures": [
    ...     {"name": "a", "range": [0, 1], "importance": 0.5, "colour": [1, 1, 1]}]})
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     save_spec(spec, os.path.join(tmp, "a.json"))
    ...     load_spec(os.path.join(tmp, "a.json")) == spec
    True
    """
    path = Path(path)
    d = spec_to_dict(parse_spec_dict(spec_to_dict(spec), "spec")[0])  # validates
    if spec.labels_file is not None and Path(spec.labels_file).is_absolute():
        try:
            base = path.parent if relative_to is None else Path(relative_to)
            d["labels"] = os.path.relpath(spec.labels_file, base.resolve())
        except ValueError:  # another drive on Windows
            d["labels"] = str(spec.labels_file)
    text = _dumps(d) + "\n"
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise DVRInputError(f"{path}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    mask = os.umask(0o022)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)  # mkstemp makes 0600; outputs follow the umask like the rest
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def attach_labels(volume, spec: StructureSpec):
    """Return ``volume`` with the label volume of ``spec.labels_file`` attached.

    Unchanged when the spec names no label file.  The label file must have the volume's dims;
    integer-valued float labels are accepted.  A 3D Slicer segmentation must have the volume's
    spacing and may cover part of it (placed by its origin, see
    :func:`dvr_perception.structures.slicer.segmentation_labels`).

    Raises
    ------
    DVRInputError
        Naming the label file when it cannot be read, has other dims or non-integer values.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> vol = Volume(np.zeros((2, 2, 2), np.uint8))
    >>> spec = spec_from_dict({"version": 1, "structures": [
    ...     {"name": "air", "range": [0, 10], "importance": 0.5, "colour": [1, 1, 1]}]})
    >>> attach_labels(vol, spec) is vol
    True
    """
    if spec.labels_file is None:
        return volume
    from dataclasses import replace

    from dvr_perception.volume.io import load_volume

    path = spec.labels_file
    from dvr_perception.structures.slicer import is_segmentation, segmentation_labels

    if is_segmentation(path):
        return replace(volume, labels=segmentation_labels(path, volume))
    lab = load_volume(path)
    data = lab.data
    if data.shape != volume.data.shape:
        raise DVRInputError(
            f"labels file {path}: dims {lab.dims} do not match the volume's dims {volume.dims}"
        )
    if data.dtype.kind == "f":
        if not np.all(np.isfinite(data)) or np.any(data != np.round(data)):
            raise DVRInputError(f"labels file {path}: label values must be integers")
    elif data.dtype.kind not in "ui":
        raise DVRInputError(f"labels file {path}: expected integer labels, got {data.dtype}")
    if data.dtype.kind == "f" or data.dtype.itemsize > 4 or data.dtype == np.uint32:
        # labels are 32-bit ids, as in a spec; stored as int32
        lo, hi = float(data.min()), float(data.max())
        if lo < -(2**31) or hi > 2**31 - 1:
            raise DVRInputError(
                f"labels file {path}: label values must be 32-bit integers "
                f"(-2147483648 to 2147483647), got {lo:.0f} to {hi:.0f}"
            )
        data = data.astype(np.int32)
    return replace(volume, labels=data)


def check_spec_for_volume(spec: StructureSpec, volume) -> list[str]:
    """Check that every structure of ``spec`` can appear in ``volume``.

    Returns (and emits as :class:`DVRWarning`) one message per range structure whose range
    holds no voxel and per label structure whose id is absent from the label volume.

    Raises
    ------
    DVRInputError
        If the spec has label structures and ``volume.labels`` is ``None``.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> vol = Volume(np.zeros((2, 2, 2), np.uint8))
    >>> spec = spec_from_dict({"version": 1, "structures": [
    ...     {"name": "air", "range": [0, 10], "importance": 0.5, "colour": [1, 1, 1]}]})
    >>> check_spec_for_volume(spec, vol)
    []
    """
    data = volume.data
    found: list[str] = []
    lo_v, hi_v = volume.scalar_range
    counts = None
    if data.dtype.kind in "ui" and hi_v - lo_v < 2**20:
        counts = np.cumsum(int_histogram(data, int(lo_v), int(hi_v - lo_v) + 1))
    for s in spec.structures:
        if s.range is not None:
            lo, hi = s.range
            if counts is not None:
                a = int(np.ceil(lo - lo_v))
                b = int(np.floor(hi - lo_v))
                a, b = max(a, 0), min(b, len(counts) - 1)
                n = 0 if a > b else int(counts[b] - (counts[a - 1] if a > 0 else 0))
            else:
                n = int(np.count_nonzero((data >= lo) & (data <= hi)))
            if n == 0:
                found.append(
                    f"structure {s.name!r}: range [{lo:g}, {hi:g}] holds no voxel of volume "
                    f"{volume.name!r} (values {lo_v:g} to {hi_v:g})"
                )
        else:
            if volume.labels is None:
                raise DVRInputError(
                    f"structure {s.name!r}: label {s.label} needs a label volume, but volume "
                    f"{volume.name!r} has none"
                )
            if not np.any(volume.labels == s.label):
                found.append(
                    f"structure {s.name!r}: label {s.label} does not occur in the label volume "
                    f"of {volume.name!r}"
                )
    for msg in found:
        warnings.warn(msg, DVRWarning, stacklevel=2)
    return found
