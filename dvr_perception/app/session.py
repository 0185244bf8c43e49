"""What the web app works on, without any web framework: volume, spec, undo stack, files, measures.

:class:`Session` holds the volume, the structure spec shown, an undo stack of specs and the
folders the app may touch.  The *data folder* is only read: its volumes and spec JSON files
are offered by name.  Everything the app writes goes into its *state folder* (per user, see
:func:`default_state_dir`): uploaded volumes (``uploads/``, offered as ``uploaded/NAME``),
saved settings (``settings/``, offered as ``saved/NAME``) and, unless another *export folder*
is chosen when the server starts, the exports (``exports/``).  A client only ever picks one of
the names offered or gives a plain file name (no folders) to save under; the server resolves
it inside its folder.  Every method calls the library
(:mod:`dvr_perception.volume`, :mod:`~dvr_perception.structures`,
:mod:`~dvr_perception.measures`, :mod:`~dvr_perception.export`) and raises
:class:`~dvr_perception.errors.DVRInputError` with a one-line message for bad input, which the
app shows in the page.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dvr_perception._deprecation import renamed_keyword
from dvr_perception.errors import DVRInputError

__all__ = [
    "MAX_UPLOAD_BYTES",
    "MEASURE_SIZE",
    "ORIENTATION_CODES",
    "PHANTOM",
    "SPEC_SUFFIXES",
    "VOLUME_SUFFIXES",
    "Measures",
    "Session",
    "default_state_dir",
    "hex_to_rgb",
    "measure_camera",
    "orientation_choices",
    "plain_name",
    "rgb_to_hex",
]

#: Name of the built-in phantom in the volume list.
PHANTOM = "phantom"
#: File suffixes listed as volumes in the data folder.
VOLUME_SUFFIXES = (".nhdr", ".nrrd", ".mha", ".mhd", ".vti", ".nii", ".nii.gz")
#: File suffixes listed as structures (settings) in the data folder: spec JSON files and 3D
#: Slicer segmentations (never listed as volumes).
SPEC_SUFFIXES = (".json", ".seg.nrrd", ".seg.nhdr")
#: Long side, in pixels, of the camera the measures and the optimiser are evaluated on.
MEASURE_SIZE = 256
#: Most specs kept for undo.
UNDO_DEPTH = 50
#: Largest volume file accepted by the upload field.
MAX_UPLOAD_BYTES = 64 * 1024 * 1024
#: Largest voxel data (decompressed) an uploaded volume may hold.
MAX_VOLUME_BYTES = 512_000_000
#: Orientation codes the Data screen offers for a file that records none ("" is as stored).
ORIENTATION_CODES = ("LPS", "LPI", "RAS", "RAI", "LAS", "LAI", "RPS", "RPI")
#: How the app's note on a patient view of a file without orientation says to fix it.
ORIENTATION_FIX = (
    "choose its orientation in the Data screen's Orientation field, e.g. LPI when slice 0 is "
    "the top of the head"
)
#: Prefix of the uploaded volumes in the volume list.
UPLOADED = "uploaded/"
#: Prefix of the settings saved by the app in the settings list.
SAVED = "saved/"
#: A plain file name: no folders, no leading dot, at most 128 characters.
_PLAIN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,127}")


def default_state_dir() -> Path:
    """Return the per-user folder the app writes into (created when first needed).

    ``platformdirs.user_state_dir`` when installed, else ``$XDG_STATE_HOME/dvr-perception``
    or ``~/.local/state/dvr-perception``.
    """
    try:
        from platformdirs import user_state_dir
    except ImportError:
        base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
        return Path(base) / "dvr-perception"
    return Path(user_state_dir("dvr-perception", appauthor=False))


def plain_name(text, what: str, suffixes=None) -> str:
    """Check that ``text`` is a plain file name (no folder) with one of ``suffixes``.

    Examples
    --------
    >>> plain_name("my_spec.json", "settings file", (".json",))
    'my_spec.json'
    """
    name = str(text or "").strip()
    if not _PLAIN.fullmatch(name):
        raise DVRInputError(
            f"{what} {name[:80]!r}: expected a plain file name (letters, digits, '.', '_', '+', "
            "'-'; no folders)"
        )
    if suffixes and not name.lower().endswith(tuple(suffixes)):
        raise DVRInputError(f"{what} {name}: expected a name ending in {', '.join(suffixes)}")
    return name


def _ends(name: str, suffixes) -> bool:
    return name.lower().endswith(tuple(suffixes))


def rgb_to_hex(color) -> str:
    """Return ``#rrggbb`` for a colour with components in [0, 1].

    Examples
    --------
    >>> rgb_to_hex((1.0, 0.5, 0.0))
    '#ff8000'
    """
    return "#" + "".join(f"{round(min(max(float(c), 0.0), 1.0) * 255):02x}" for c in color)


def hex_to_rgb(text: str) -> tuple[float, float, float]:
    """Parse ``#rrggbb`` into a colour with components in [0, 1].

    Examples
    --------
    >>> hex_to_rgb("#ff8000")
    (1.0, 0.5019607843137255, 0.0)
    """
    s = str(text).strip().lstrip("#")
    if len(s) != 6:
        raise DVRInputError(f"colour: expected #rrggbb, got {text!r}")
    try:
        r, g, b = (int(s[i : i + 2], 16) / 255.0 for i in (0, 2, 4))
    except ValueError:
        raise DVRInputError(f"colour: expected #rrggbb, got {text!r}") from None
    return (r, g, b)


def measure_camera(camera, size: int = MEASURE_SIZE):
    """Return ``camera`` with its long side reduced to at most ``size`` pixels (same view).

    Examples
    --------
    >>> from dvr_perception.rays import Camera
    >>> cam = measure_camera(Camera(width=1024, height=512), 256)
    >>> (cam.width, cam.height)
    (256, 128)
    """
    long = max(camera.width, camera.height)
    if long <= size:
        return camera
    s = size / long
    return camera.with_size(max(8, round(camera.width * s)), max(8, round(camera.height * s)))


@dataclass(frozen=True)
class Measures:
    """The three measures of one view: the errors and their per-pixel deviation images.

    ``shares`` maps each structure to its ``visible`` and ``wanted`` (target, D1) share of the
    image; ``present`` is the per-pixel bitmask of the structures a ray meets (bit ``k`` =
    structure ``k``) and ``share_images`` the per-pixel visible shares ``(K, H, W)``, used to
    list the structures inside a lens with their share there.
    """

    E_v: float
    E_s: float
    E_t: float
    images: dict
    shares: dict = None
    present: np.ndarray = None
    share_images: np.ndarray = None

    def as_state(self) -> dict:
        """Numbers for the page (three significant digits)."""
        return {k: float(f"{getattr(self, k):.3g}") for k in ("E_v", "E_s", "E_t")}


class Session:
    """Volume, spec, undo stack and the folders of one app instance.

    Parameters
    ----------
    data_dir : str or Path, optional
        Folder of volumes and spec files, only read; ``None`` offers the phantom and the
        app's own files only.
    export_dir : str or Path, optional
        Folder the exports, calibration curves and ranking answers are written to (created
        when first needed); default ``exports`` in the state folder.
    state_dir : str or Path, optional
        Folder the app writes uploads and saved settings to; default
        :func:`default_state_dir`.
    phantom_size : int
        Edge length of the built-in phantom.
    max_volume_bytes : int
        Largest voxel data (decompressed) an uploaded volume may hold.
    """

    def __init__(
        self,
        data_dir=None,
        export_dir=None,
        *,
        state_dir=None,
        phantom_size: int = 96,
        max_volume_bytes: int = MAX_VOLUME_BYTES,
    ):
        self.data_dir = Path(data_dir).resolve() if data_dir is not None else None
        if self.data_dir is not None and not self.data_dir.is_dir():
            raise DVRInputError(f"--data-dir {data_dir}: not a directory")
        self.state_dir = Path(state_dir if state_dir is not None else default_state_dir())
        self.state_dir = self.state_dir.resolve()
        self.upload_dir = self.state_dir / "uploads"
        self.settings_dir = self.state_dir / "settings"
        self.export_dir = Path(export_dir if export_dir is not None else self.state_dir / "exports")
        self.export_dir = self.export_dir.resolve()
        self.phantom_size = int(phantom_size)
        self.max_volume_bytes = int(max_volume_bytes)
        self.volume = None
        self.volume_name = ""
        self.read_volume = None  # the volume as read from its file (no orientation, labels)
        self.orientation = None  # the orientation code given to it (None: as the file says)
        self.base_volume = None  # the volume as loaded and oriented, before a spec's label file
        self.labels_file = None  # the label file whose labels ``volume`` carries
        self.spec = None
        self.spec_source = ""
        self.undo_stack: list = []
        self.undo_labels: list[str] = []
        self.calibration = None
        self.calibration_name = ""
        self._curvature = (None, None)  # (key, curvature volume) of the last spec's structures

    # -- files -------------------------------------------------------------------------------
    @staticmethod
    def _listed(folder, suffixes) -> list[str]:
        """Names of the regular, not hidden files in ``folder`` with one of ``suffixes``."""
        if folder is None or not folder.is_dir():
            return []
        return sorted(
            p.name
            for p in folder.iterdir()
            if p.is_file() and not p.name.startswith(".") and p.name.lower().endswith(suffixes)
        )

    def volume_choices(self) -> list[str]:
        """List the phantom, the data folder's volumes and the uploaded ones (``uploaded/``).

        3D Slicer segmentations (``*.seg.nrrd``, ``*.seg.nhdr``) are structures, not volumes:
        :meth:`spec_choices` offers them.
        """
        segs = SPEC_SUFFIXES[1:]
        names = [n for n in self._listed(self.data_dir, VOLUME_SUFFIXES) if not _ends(n, segs)]
        ups = [n for n in self._listed(self.upload_dir, VOLUME_SUFFIXES) if not _ends(n, segs)]
        return [PHANTOM, *names] + [UPLOADED + n for n in ups]

    def spec_choices(self) -> list[str]:
        """List the data folder's spec JSON files and segmentations, and the saved specs.

        The saved ones (JSON only) are prefixed ``saved/``.
        """
        names = self._listed(self.data_dir, SPEC_SUFFIXES)
        return names + [SAVED + n for n in self._listed(self.settings_dir, (".json",))]

    def data_path(self, text: str, *, must_exist: bool = True) -> Path:
        """Resolve ``text`` inside the data folder; refuse anything outside it."""
        if self.data_dir is None:
            raise DVRInputError("no data folder: start the app with --data-dir DIR to use files")
        if not str(text or "").strip():
            raise DVRInputError("file name: expected a file name in the data folder, got nothing")
        path = (self.data_dir / str(text).strip()).resolve()
        if not path.is_relative_to(self.data_dir):
            raise DVRInputError(
                f"{text}: outside the data folder {self.data_dir}; only files in it are allowed"
            )
        if must_exist and not path.is_file():
            raise DVRInputError(f"{text}: no such file in the data folder {self.data_dir}")
        return path

    def _chosen(self, text, choices: list[str], what: str, saved_prefix: str, saved_dir) -> Path:
        """Return the file of one of ``choices`` (the server's list); refuse any other name.

        A listed name is a file directly inside its folder (a folder listing holds no ``/``),
        so the only ``/`` in a choice is the one of the ``saved/`` or ``uploaded/`` prefix.
        """
        name = str(text or "").strip()
        if name not in choices:
            shown = ", ".join(choices[:8]) + (", ..." if len(choices) > 8 else "")
            raise DVRInputError(
                f"{name[:80] or '(nothing)'}: not one of the {what} offered "
                f"({shown or 'none'}); only these files can be opened"
            )
        if name.startswith(saved_prefix):
            folder, base = saved_dir, name[len(saved_prefix) :]
        else:
            folder, base = self.data_dir, name
        if folder is None or "/" in base or base in ("", ".", ".."):
            raise DVRInputError(f"{name[:80]}: not a file of the app's folders")
        return folder / base

    def writable_dir(self, folder: Path) -> Path:
        """Create ``folder`` (private to the user when it is in the state folder)."""
        mode = 0o700 if folder.is_relative_to(self.state_dir) else 0o777
        if folder.is_relative_to(self.state_dir):
            self.state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        folder.mkdir(parents=True, exist_ok=True, mode=mode)
        return folder

    def load_volume(self, name: str, *, orientation=None):
        """Load the phantom or an offered volume with its preset (by data checksum) or a proposal.

        ``orientation`` (``dvr-perception app --orientation CODE``) declares where the file's
        index axes point, as the other commands' ``--orientation`` does.
        """
        from dvr_perception.structures import check_spec_for_volume, make_phantom

        if name == PHANTOM:
            volume, spec = make_phantom(size=self.phantom_size)
            source = "built-in phantom settings"
        else:
            path = self._chosen(
                name, self.volume_choices()[1:], "volumes", UPLOADED, self.upload_dir
            )
            from dvr_perception.inputs import load_volume_and_spec

            # the command line's loader: a preset by the data's checksum, else a proposal
            volume, spec, _, line = load_volume_and_spec(str(path))
            source = line.removeprefix("structures: ").removeprefix("structures ")
            # "preset 'x' (...)" / "proposed from the data (...)"
        read, orientation = volume, _code(orientation)
        base = volume = _oriented(read, orientation)
        labels_file = None
        if spec.labels_file is not None:  # a preset of the server's own with a label volume
            from dvr_perception.structures.io import attach_labels

            # labels in the file's order, re-ordered with the data (as the command line does)
            volume = _oriented(attach_labels(read, spec), orientation)
            labels_file = str(Path(spec.labels_file).resolve())
        check_spec_for_volume(spec, volume)
        self.read_volume, self.orientation = read, orientation
        self.base_volume, self.labels_file = base, labels_file
        self.volume, self.volume_name = volume, name
        self.spec, self.spec_source = spec, source
        self.undo_stack.clear()
        self.undo_labels.clear()
        return volume, spec

    def load_spec_file(self, text: str):
        """Read an offered spec JSON or Slicer segmentation and check it for the volume.

        A segmentation (``*.seg.nrrd``/``*.seg.nhdr`` in the data folder) becomes one label
        structure per segment
        (:func:`~dvr_perception.structures.slicer.spec_from_segmentation`).  The label volume
        of a spec with a ``labels`` file is attached to the volume
        (:func:`~dvr_perception.structures.io.attach_labels`); the label file must lie in the
        data folder or the settings folder.  Everything is read and checked before the
        session's volume and spec change, so a bad file leaves them as they were.
        """
        from dvr_perception.structures import check_spec_for_volume, load_spec
        from dvr_perception.structures.slicer import is_segmentation, spec_from_segmentation

        if self.volume is None:
            raise DVRInputError(f"{text}: load a volume before its structures")
        path = self._chosen(text, self.spec_choices(), "settings files", SAVED, self.settings_dir)
        if path.name.lower().endswith(SPEC_SUFFIXES[1:]) and is_segmentation(path):
            spec = spec_from_segmentation(path, self.volume)
        else:
            spec = load_spec(path)
        volume, labels = self.with_labels(spec, source=str(text))
        check_spec_for_volume(spec, volume)
        self.push_undo(f"load {text}")
        self.volume, self.labels_file = volume, labels
        self.spec, self.spec_source = spec, str(text)
        return spec

    def with_labels(self, spec, *, source: str = "spec"):
        """Return the session's volume with the label volume of ``spec``, and that file.

        The volume as loaded (:attr:`base_volume`) when ``spec`` names no ``labels`` file, the
        current one when it already carries that file's labels.  A label file outside the data
        folder and the settings folder is refused (no file a client names may be read outside
        the app's folders).

        Returns
        -------
        volume : Volume
        labels_file : str or None
            The resolved label file the returned volume carries.
        """
        from dvr_perception.structures.io import attach_labels

        if spec.labels_file is None:
            return self.base_volume, None
        path = Path(spec.labels_file).resolve()
        allowed = [d for d in (self.data_dir, self.settings_dir.resolve()) if d is not None]
        if not any(path.is_relative_to(d) for d in allowed):
            raise DVRInputError(
                f"{source}: labels file {spec.labels_file} is outside the data folder and the "
                "settings folder; only label files in them are read"
            )
        if self.labels_file == str(path):
            return self.volume, self.labels_file
        volume = attach_labels(self.read_volume, replace(spec, labels_file=str(path)))
        return _oriented(volume, self.orientation), str(path)

    def set_orientation(self, code):
        """Declare where the index axes of a file that records no orientation point.

        ``code``: three letters as ``--orientation`` takes them (e.g. ``"LPI"``, slice 0 at
        the top of the head); ``""`` or ``None`` goes back to the axes as stored (taken as L,
        P, S).  The volume and the spec's label volume are re-ordered into patient LPS
        (:func:`~dvr_perception.volume.orient.reorient`); everything is checked before the
        session changes.  The volume changes as when one is loaded, so, as a load does, this
        clears the undo stack (choose the previous code to go back).  Returns the volume.
        """
        from dvr_perception.structures import check_spec_for_volume

        if self.volume is None:
            raise DVRInputError("Orientation: load a volume first")
        orientation = _code(code)
        if self.read_volume.oriented:
            raise DVRInputError(
                f"Orientation {orientation or 'as stored'}: {self.volume_name} records its "
                "patient orientation; a code is only for files that record none"
            )
        base = volume = _oriented(self.read_volume, orientation)
        if self.labels_file is not None:  # labels in the file's order: re-ordered with the data
            from dvr_perception.structures.io import attach_labels

            labelled = replace(self.spec, labels_file=self.labels_file)
            volume = _oriented(attach_labels(self.read_volume, labelled), orientation)
        check_spec_for_volume(self.spec, volume)
        self.orientation, self.base_volume, self.volume = orientation, base, volume
        self.undo_stack.clear()
        self.undo_labels.clear()
        return volume

    def patient_view_note(self) -> str | None:
        """Return the note on a patient view of a volume whose file records no orientation.

        ``None`` once the volume is oriented (by its file or an orientation code).
        """
        from dvr_perception.volume.orient import orientation_note

        return None if self.volume is None else orientation_note(self.volume, ORIENTATION_FIX)

    def save_spec_file(self, text: str) -> str:
        """Write the current spec as JSON into the settings folder; return its offered name."""
        from dvr_perception.structures.io import save_spec

        name = plain_name(str(text or "").strip().removeprefix(SAVED), "settings file", (".json",))
        save_spec(self.spec, self.writable_dir(self.settings_dir) / name)
        return SAVED + name

    def export(self, plotter=None, *, legend=None) -> list[Path]:
        """Write view PNG, spec JSON, ParaView preset and Slicer ``.vp.json`` to the export dir.

        With ``legend`` (the keywords of :func:`~dvr_perception.app.export_image.with_legend`
        but the image) the PNG gets the legend and colour bar in a panel on its right.
        """
        from dvr_perception.app.export_image import save_png, with_legend
        from dvr_perception.export import save_paraview_preset, save_slicer_vp
        from dvr_perception.structures.io import save_spec

        self.writable_dir(self.export_dir)
        stem = self.export_dir / (self.volume.name or "volume")
        out = []
        if plotter is not None:
            image = plotter.screenshot(None, return_img=True)
            if legend is not None:
                image = with_legend(image, **legend)
            out.append(save_png(image[..., :3], stem.with_name(stem.name + "_view.png")))
        spec_path = stem.with_name(stem.name + "_spec.json")
        save_spec(self.spec, spec_path)
        out.append(spec_path)
        out.append(save_paraview_preset(self.spec, stem.with_name(stem.name + "_paraview.json")))
        out.append(save_slicer_vp(self.spec, stem.with_name(stem.name + ".vp.json"), self.volume))
        return [Path(p) for p in out]

    def snapshot(self) -> tuple:
        """Return what :meth:`restore` needs to undo a load (volume, labels, spec, undo)."""
        return (
            self.volume,
            self.labels_file,
            self.spec,
            self.spec_source,
            list(self.undo_stack),
            list(self.undo_labels),
        )

    def restore(self, snapshot: tuple) -> None:
        """Go back to a :meth:`snapshot` (e.g. when the view cannot show a loaded spec)."""
        self.volume, self.labels_file, self.spec, self.spec_source = snapshot[:4]
        self.undo_stack[:] = snapshot[4]
        self.undo_labels[:] = snapshot[5]

    # -- editing -----------------------------------------------------------------------------
    def push_undo(self, label: str = "edit") -> None:
        """Remember the current spec before a change described by ``label``."""
        if self.spec is not None:
            self.undo_stack.append(self.spec)
            self.undo_labels.append(str(label))
            del self.undo_stack[:-UNDO_DEPTH]
            del self.undo_labels[:-UNDO_DEPTH]

    def undo(self, steps: int = 1):
        """Go back ``steps`` changes; return the restored spec (``None``: nothing to undo)."""
        n = int(steps)
        if n < 1 or n > len(self.undo_stack):
            return None
        spec = self.undo_stack[-n]
        self.volume, self.labels_file = self.with_labels(spec, source="undo")
        self.spec = spec
        del self.undo_stack[-n:]
        del self.undo_labels[-n:]
        return self.spec

    def history_rows(self) -> list[dict]:
        """List the changes that can be undone, newest first: ``{"steps", "label"}``."""
        n = len(self.undo_labels)
        return [{"steps": n - k, "label": self.undo_labels[k]} for k in range(n - 1, -1, -1)]

    @renamed_keyword("color", "colour", name="Session.set_structure")
    def set_structure(
        self, index: int, *, importance=None, colour=None, value_range=None, opacity=None
    ):
        """Change one structure's importance (its opacity then follows it), colour or range.

        ``opacity`` sets the rendering opacity alone (the transfer-function view's handle);
        ``colour`` is ``#rrggbb`` (``color=`` is a deprecated alias).
        """
        k = int(index)
        if not 0 <= k < len(self.spec.structures):
            raise DVRInputError(f"structure {index}: no such structure")
        s = self.spec.structures[k]
        if value_range is not None:
            if s.range is None:
                raise DVRInputError(f"{s.name}: a label structure has no value range")
            try:
                lo, hi = (float(v) for v in value_range)
            except (TypeError, ValueError):
                raise DVRInputError(
                    f"range of {s.name}: expected two numbers, got {value_range!r}"
                ) from None
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise DVRInputError(
                    f"range of {s.name}: expected two numbers with low < high, got {lo:g} to {hi:g}"
                )
            s = replace(s, range=(lo, hi))
        if importance is not None:
            v = float(importance)
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise DVRInputError(f"importance of {s.name}: expected 0 to 1, got {importance}")
            s = replace(s, importance=v, opacity=None)
        if opacity is not None:
            v = float(opacity)
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise DVRInputError(f"opacity of {s.name}: expected 0 to 1, got {opacity}")
            s = replace(s, opacity=v)
        if colour is not None:
            s = replace(s, colour=hex_to_rgb(colour))
        if s == self.spec.structures[k]:
            return self.spec
        what = "importance" if importance is not None else "colour"
        what = "opacity" if opacity is not None else what
        what = "range" if value_range is not None else what
        self.push_undo(f"{what} of {s.name}")
        structures = list(self.spec.structures)
        structures[k] = s
        self.spec = replace(self.spec, structures=tuple(structures))
        if value_range is not None:
            from dvr_perception.structures import check_spec_for_volume

            check_spec_for_volume(self.spec, self.volume)  # warns when the range is empty
        return self.spec

    def structure_rows(self) -> list[dict]:
        """One JSON-ready row per structure for the page's table."""
        return [
            {
                "index": k,
                "name": s.name,
                "importance": round(float(s.importance), 3),
                "opacity": round(float(s.render_opacity), 3),
                "color": rgb_to_hex(s.colour),
                "range": [round(float(v), 1) for v in s.range] if s.range else None,
                "label": None if s.label is None else int(s.label),
            }
            for k, s in enumerate(self.spec.structures)
        ]

    # -- measures ----------------------------------------------------------------------------
    def curvature(self, spec=None):
        """Return the curvature source of ``spec`` (default the current one), cached.

        It depends only on how the voxels are classified (the structures' ranges and labels),
        not on opacity, colour or lighting: computing it took most of a re-measure (about 5 s
        on cthead), so it is kept until a range or label changes.
        """
        from dvr_perception.rays.curvature_field import curvature_source

        spec = self.spec if spec is None else spec
        # the volume itself (compared by identity): an id could be reused by a later volume
        key = (self.volume, tuple((s.range, s.label, s.edge) for s in spec.structures))
        old = self._curvature[0]
        if old is None or old[0] is not key[0] or old[1] != key[1]:
            self._curvature = (key, curvature_source(self.volume, spec))
        return self._curvature[1]

    def measure(self, camera, spec=None) -> Measures:
        """Analyse ``spec`` (default the current one) from ``camera`` (reduced): E_v, E_s, E_t."""
        from dvr_perception.rays.engine import analyze

        spec = self.spec if spec is None else spec
        cam = measure_camera(camera)
        curvature = self.curvature(spec)
        analysis = analyze(self.volume, spec, cam, curvature=curvature)
        return self.measures_of(analysis, spec)

    def measures_of(self, analysis, spec) -> Measures:
        """Compute E_v, E_s, E_t and the maps of a ray analysis of ``spec`` (no rendering)."""
        from dvr_perception.measures import all_measures

        v, s, t = all_measures(analysis, spec, calibration=self.calibration)
        empty = ~v.nonempty  # no map where nothing is rendered: the background stays visible
        images = {
            name: np.where(empty, np.nan, np.asarray(r.deviation, dtype=np.float32))
            for name, r in (("visibility", v), ("shape", s), ("transparency", t))
        }
        shares = {
            name: {
                "visible": float(d["visible_share"]),
                "wanted": float(d["target_share"]),
            }
            for name, d in v.per_structure.items()
        }
        present = np.asarray(analysis.present, dtype=np.uint32)
        share_images = np.asarray(analysis.visible_share, dtype=np.float32)
        return Measures(
            float(v.E_v), float(s.E_s), float(t.E_t), images, shares, present, share_images
        )

    def region_structures(self, present, mask, share_images=None) -> list[dict]:
        """Structures met by rays inside ``mask`` (same shape as ``present``), most first.

        Returns ``{"index", "name", "fraction", "visible"}`` rows: ``fraction`` is the share of
        the region's pixels whose ray meets the structure, ``visible`` its mean visible share
        over those pixels (from ``share_images``, ``(K, H, W)``; ``None`` without them).
        """
        m = np.asarray(mask, dtype=bool)
        inside = np.asarray(present)[m]
        rows = []
        if inside.size == 0:
            return rows
        for k, s in enumerate(self.spec.structures):
            hit = ((inside >> np.uint32(k)) & np.uint32(1)).astype(bool)
            frac = float(hit.mean())
            if frac > 0:
                visible = None
                if share_images is not None and k < len(share_images):
                    visible = round(float(np.asarray(share_images[k])[m][hit].mean()), 3)
                rows.append(
                    {"index": k, "name": s.name, "fraction": round(frac, 3), "visible": visible}
                )
        return sorted(rows, key=lambda r: -r["fraction"])

    # -- calibration -------------------------------------------------------------------------
    def use_calibration(self, curve, name: str = "") -> None:
        """Measure transparency through ``curve`` from now on (``None``: no calibration)."""
        self.calibration = curve
        self.calibration_name = str(name) if curve is not None else ""

    # -- upload ------------------------------------------------------------------------------
    def store_upload(self, name: str, content: bytes, *, max_bytes: int = MAX_UPLOAD_BYTES):
        """Check an uploaded volume file, save it into the uploads folder, return its name.

        The file must be no larger than ``max_bytes``, have a single-file volume suffix, pass
        :func:`~dvr_perception.app.uploads.check_volume_bytes` (no detached data file, voxel
        data within ``max_volume_bytes``, checked without decompressing it into memory) and
        load as a volume; otherwise nothing is kept and :class:`DVRInputError` says why.
        The name returned is the one offered in :meth:`volume_choices` (``uploaded/NAME``).
        """
        from dvr_perception.app.uploads import check_volume_bytes
        from dvr_perception.volume import load_volume

        base = Path(str(name or "")).name
        if not base.lower().endswith(VOLUME_SUFFIXES):
            raise DVRInputError(
                f"upload {base or '(no name)'}: not a volume file; expected one of "
                f"{', '.join(VOLUME_SUFFIXES)}"
            )
        base = plain_name(base, "upload")
        size = len(content)
        if size > max_bytes:
            raise DVRInputError(
                f"upload {base}: {size / 1e6:.1f} MB is larger than the limit of "
                f"{max_bytes / 1e6:.1f} MB"
            )
        check_volume_bytes(base, content, max_volume_bytes=self.max_volume_bytes)
        path = self.writable_dir(self.upload_dir) / base
        tmp = path.with_name(f".upload-{path.name}")
        tmp.write_bytes(content)
        try:
            load_volume(tmp)
        except Exception as exc:
            tmp.unlink(missing_ok=True)
            why = str(exc).replace(f"{tmp}: ", "").replace(str(tmp), base)
            raise DVRInputError(f"upload {base}: not a readable volume ({why})") from None
        tmp.replace(path)
        return UPLOADED + path.name


def orientation_choices() -> list[dict]:
    """Return the Data screen's Orientation items (``{"title", "value"}``), as stored first.

    Examples
    --------
    >>> orientation_choices()[2]
    {'title': 'LPI: x left, y posterior, z inferior (slice 0 at the top)', 'value': 'LPI'}
    """
    words = dict(zip("LRPASI", ("left", "right", "posterior", "anterior", "superior",
                                "inferior"), strict=True))  # fmt: skip
    items = [{"title": "as stored (taken as L, P, S)", "value": ""}]
    for code in ORIENTATION_CODES:
        x, y, z = (words[c] for c in code)
        top = " (slice 0 at the top)" if code[2] == "I" else ""
        items.append({"title": f"{code}: x {x}, y {y}, z {z}{top}", "value": code})
    return items


def _code(code) -> str | None:
    """Return an orientation code, checked and upper-case (``None`` for none given)."""
    from dvr_perception.volume.orient import parse_orientation

    text = str(code or "").strip().upper()
    if not text:
        return None
    parse_orientation(text, name="Orientation")
    return text


def _oriented(volume, code):
    """``volume`` re-ordered by orientation ``code`` (unchanged for ``None``)."""
    from dvr_perception.volume.orient import reorient

    return volume if code is None else reorient(volume, code, name=f"Orientation {code}")
