"""Patient orientation: build a :class:`Volume` from a file's axes, canonical data order.

Convention (as DICOM, ITK and 3D Slicer): world coordinates are patient **LPS** -- +x towards
the patient's left, +y posterior, +z superior -- in millimetres.  A file's geometry is an
origin (the world position of the first voxel) and one world vector per index axis (x, y, z;
its length is the spacing).  NIfTI and FreeSurfer store RAS; :func:`ras_to_lps` turns such a
geometry into LPS.

:func:`canonical` re-orders the data so that every index axis runs along the world axis it is
closest to, in the positive direction: a volume whose axes are flips or permutations of the
world axes (the usual case: DICOM slices stored head first, NRRD with a negative direction,
a NIfTI in RAS) becomes axis-aligned with the identity direction, exactly and without
resampling.  Only a truly oblique volume keeps a rotation in ``Volume.direction``; the engine
renders it in its own frame and a camera given in patient terms is rotated into that frame
(:meth:`dvr_perception.rays.camera.Camera.for_volume`).
"""

from __future__ import annotations

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume.volume import Volume

__all__ = [
    "canonical",
    "file_order",
    "from_axes",
    "orientation_note",
    "parse_orientation",
    "ras_to_lps",
    "reorient",
]

#: Diagonal that turns RAS coordinates into LPS (and back).
_FLIP_RAS = np.array([-1.0, -1.0, 1.0])


def ras_to_lps(axes, origin) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(axes, origin)`` of a RAS geometry expressed in LPS.

    Parameters
    ----------
    axes : array-like, 3 x 3
        Columns are the world vectors of one step along index x, y, z.
    origin : array-like, 3
        World position of the first voxel.

    Examples
    --------
    >>> a, o = ras_to_lps(np.eye(3), [1.0, 2.0, 3.0])
    >>> np.diag(a).tolist(), o.tolist()
    ([-1.0, -1.0, 1.0], [-1.0, -2.0, 3.0])
    """
    return _FLIP_RAS[:, None] * np.asarray(axes, float), _FLIP_RAS * np.asarray(origin, float)


def from_axes(
    data: np.ndarray, axes, origin, *, name: str, source: str, where: str = "", oriented=True
) -> Volume:
    """Build a canonical :class:`Volume` from data ``[z, y, x]`` and a file's axis vectors.

    Parameters
    ----------
    data : numpy.ndarray
        Voxels indexed ``[z, y, x]``.
    axes : array-like, 3 x 3
        Columns: world (LPS) vector of one step along index x, y and z.
    origin : array-like, 3
        World position of ``data[0, 0, 0]``.
    name, source : str
        Stored on the volume.
    where : str, optional
        Prefix of error messages (the file and field); default ``source``.
    oriented : bool, optional
        ``False`` when the file records no patient orientation (``axes`` are a guess):
        stored as ``Volume.oriented``.

    Raises
    ------
    DVRInputError
        Zero, non-finite or non-orthogonal axis vectors (sheared grids are not supported).

    Examples
    --------
    >>> d = np.arange(8, dtype=np.uint8).reshape(2, 2, 2)
    >>> v = from_axes(d, np.diag([1.0, 1.0, -2.0]), [0, 0, 2], name="v", source="")
    >>> v.spacing, v.origin, int(v.data[0, 0, 0])
    ((1.0, 1.0, 2.0), (0.0, 0.0, 0.0), 4)
    """
    where = where or source or name
    m = np.asarray(axes, float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise DVRInputError(f"{where}: expected three finite 3-D axis vectors, got {m.tolist()}")
    with np.errstate(over="ignore"):
        spacing = np.linalg.norm(m, axis=0)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise DVRInputError(f"{where}: an axis vector is zero or too large ({m.T.tolist()})")
    unit = m / spacing
    gram = unit.T @ unit
    if not np.allclose(gram, np.eye(3), atol=1e-3):
        raise DVRInputError(
            f"{where}: the axis vectors {np.round(m.T, 6).tolist()} are not orthogonal; "
            "sheared grids are not supported (resample the volume first)"
        )
    return canonical_arrays(
        data, spacing, origin, unit, name=name, source=source, where=where, oriented=oriented
    )


def canonical_arrays(
    data, spacing, origin, direction, *, name, source, where, labels=None, oriented=True
):
    """Flip/permute ``data`` so the direction is as close to the identity as it can get.

    Returns the :class:`Volume` (with ``oriented`` stored on it); see :func:`canonical`.
    """
    d = np.asarray(direction, float)
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    n_old = data.shape[::-1]  # voxels along index x, y, z
    perm, signs, order, flips = _reordering(d)
    arrays = [data] if labels is None else [data, labels]
    out = []
    for arr in arrays:
        arr = np.transpose(arr, order)
        out.append(np.ascontiguousarray(np.flip(arr, flips) if flips else arr))
    new_origin = origin.copy()
    for a in range(3):
        if signs[a] < 0:
            i = perm[a]
            new_origin += d[:, i] * spacing[i] * (n_old[i] - 1)
    new_dir = d[:, perm] * signs
    try:
        return Volume(
            out[0],
            spacing=tuple(spacing[perm]),
            origin=tuple(new_origin),
            direction=new_dir,
            name=name,
            source=source,
            labels=out[1] if labels is not None else None,
            oriented=oriented,
        )
    except DVRInputError as exc:
        raise DVRInputError(f"{where}: {exc}") from None


def _reordering(d: np.ndarray):
    """``(perm, signs, order, flips)``: how :func:`canonical_arrays` re-orders ``[z, y, x]``.

    New index axis ``a`` is old axis ``perm[a]`` (flipped when ``signs[a] < 0``); on the
    array: ``np.flip(np.transpose(arr, order), flips)``.
    """
    perm = _closest_permutation(d)  # new index axis a <- old index axis perm[a]
    signs = np.array([1.0 if d[a, perm[a]] >= 0 else -1.0 for a in range(3)])
    order = (2 - perm[2], 2 - perm[1], 2 - perm[0])
    flips = tuple(2 - a for a in range(3) if signs[a] < 0)
    return perm, signs, order, flips


def file_order(values: np.ndarray, direction) -> np.ndarray:
    """Undo :func:`canonical`'s re-ordering: canonical ``[z, y, x]`` values back to file order.

    ``direction`` is the file's (an image's) direction matrix, whose flips and permutation
    :func:`canonical` applied; ``values`` has the canonical volume's shape.  The filters use
    this to write arrays computed on the canonical volume onto the image they were given.

    Examples
    --------
    >>> d = np.diag([1.0, -1.0, -1.0])
    >>> a = np.arange(8).reshape(2, 2, 2)
    >>> c = canonical_arrays(a.astype(np.uint8), (1, 1, 1), (0, 0, 0), d, name="c", source="",
    ...                      where="")
    >>> bool(np.array_equal(file_order(c.data, d), a))
    True
    """
    _perm, _signs, order, flips = _reordering(np.asarray(direction, float))
    arr = np.flip(values, flips) if flips else values
    return np.ascontiguousarray(np.transpose(arr, np.argsort(order)))


def _closest_permutation(d: np.ndarray) -> list[int]:
    """World axis a gets the index axis whose direction has the largest component along it."""
    best, best_score = [0, 1, 2], -1.0
    for p in ([0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]):
        score = sum(abs(d[a, p[a]]) for a in range(3))
        if score > best_score + 1e-9:
            best, best_score = p, score
    return best


def canonical(volume: Volume) -> Volume:
    """Return ``volume`` with its data flipped/permuted so the direction is nearest identity.

    An axis-aligned volume (direction a signed permutation) comes back with the identity
    direction, an oblique one with the smallest remaining rotation.  The world position of
    every voxel is unchanged; labels follow the data.

    Examples
    --------
    >>> d = ((-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0))
    >>> v = Volume(np.arange(8, dtype=np.uint8).reshape(2, 2, 2), origin=(5, 5, 0), direction=d)
    >>> c = canonical(v)
    >>> c.origin, c.oblique, int(c.data[0, 0, 0])
    ((4.0, 4.0, 0.0), False, 3)
    """
    return canonical_arrays(
        volume.data,
        volume.spacing,
        volume.origin,
        volume.direction,
        name=volume.name,
        source=volume.source,
        where=volume.source or volume.name,
        labels=volume.labels,
        oriented=volume.oriented,
    )


#: World (LPS) unit vector of each orientation letter.
_LETTERS = {"L": (1, 0, 0), "R": (-1, 0, 0), "P": (0, 1, 0), "A": (0, -1, 0), "S": (0, 0, 1),
            "I": (0, 0, -1)}  # fmt: skip


def parse_orientation(code, *, name: str = "--orientation") -> np.ndarray:
    """Direction matrix of a three-letter orientation code (``"LPS"``, ``"RAS"``, ``"LPI"``...).

    Letter ``a`` says where index axis ``a`` (x, y, z) points in the patient: L(eft), R(ight),
    P(osterior), A(nterior), S(uperior), I(nferior) -- the DICOM/ITK reading of a code.

    Raises
    ------
    DVRInputError
        Naming ``name`` when the code is not three letters covering the three patient axes.

    Examples
    --------
    >>> parse_orientation("LPI").T.tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]
    """
    text = str(code).strip().upper()
    cols = [_LETTERS.get(ch) for ch in text]
    axes = {abs(int(np.argmax(np.abs(c)))) for c in cols if c is not None}
    if len(text) != 3 or None in cols or len(axes) != 3:
        raise DVRInputError(
            f"{name}: expected three letters from L/R, P/A, S/I, one per patient axis, naming "
            f"where index x, y and z point (e.g. LPS, RAS, LPI), got {str(code)[:40]!r}"
        )
    return np.array(cols, dtype=float).T


def reorient(volume: Volume, code, *, name: str = "--orientation") -> Volume:
    """Declare where ``volume``'s index axes point (``code``) and bring it into patient LPS.

    For a file that records no orientation (raw data, an NRRD without ``space``): the data are
    flipped/permuted as :func:`canonical` does for a file's own directions, labels with them.
    The origin (the first voxel's position) is kept; the result is ``oriented``.

    Raises
    ------
    DVRInputError
        A bad code, or a volume that already has an oblique direction.

    Examples
    --------
    >>> v = Volume(np.arange(8, dtype=np.uint8).reshape(2, 2, 2))
    >>> int(reorient(v, "LPI").data[0, 0, 0])  # slice z = 0 was the top: now the last
    4
    """
    direction = parse_orientation(code, name=name)
    if volume.oblique:
        raise DVRInputError(
            f"{name}: volume {volume.name!r} records an oblique orientation already; "
            "an orientation code is for files that record none"
        )
    return canonical_arrays(
        volume.data, volume.spacing, volume.origin, direction, name=volume.name,
        source=volume.source, where=name, labels=volume.labels, oriented=True,
    )  # fmt: skip


#: How a command-line user declares the orientation of a file that records none.
_CLI_FIX = "give --orientation CODE, e.g. --orientation LPI when slice 0 is the top of the head"


def orientation_note(volume: Volume, fix: str | None = None) -> str | None:
    """One-line note for a patient view of a volume whose file records no orientation.

    ``None`` when ``volume.oriented``.  ``fix`` says how the user declares the orientation;
    default the command line's ``--orientation`` (the web app names its Orientation field).

    Examples
    --------
    >>> v = Volume(np.zeros((2, 2, 2), np.uint8), source="head.nhdr", oriented=False)
    >>> orientation_note(v).startswith("head.nhdr: the file records no patient orientation")
    True
    >>> orientation_note(reorient(v, "LPI")) is None
    True
    """
    if volume.oriented:
        return None
    fix = fix or _CLI_FIX
    return (
        f"{volume.source or volume.name}: the file records no patient orientation, so its "
        "index axes x, y, z were taken as L, P, S (towards the patient's left, posterior, "
        f"superior) and a patient view may show it upside down or mirrored; {fix}"
    )
