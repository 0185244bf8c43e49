"""VTK's reference frames in a child process: timed in turn with ours, its memory kept apart.

:func:`vtk_frame_process` is :func:`~dvr_perception.rays.vtk_reference.vtk_frame_timer` run
in a child Python process.  ``dvr-perception bench`` uses it so that the peak memory it
reports is the engine's own and VTK's renderer (which holds a copy of the volume and its
gradient tables: about 2 bytes a voxel beyond the data on a 16-bit CT) is measured on its
own, as a ratio.  The volume, spec and camera go to the child as files in a temporary
folder; the child answers one line of JSON per request on its stdout.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import StructureSpec
from dvr_perception.volume.volume import Volume

__all__ = ["VTKFrames", "vtk_frame_process"]

#: Seconds the child may take to load the volume and render its first frame.
START_TIMEOUT = 600.0


class VTKFrames:
    """Render one warm VTK frame per call in the child and return its seconds.

    ``peak_rss_mb`` is the child's peak resident memory (``VmHWM``), known once the ``with``
    block of :func:`vtk_frame_process` has ended (None before, or where the system does not
    report it).
    """

    def __init__(self, proc: subprocess.Popen) -> None:
        self._proc = proc
        self.peak_rss_mb: float | None = None

    def __call__(self) -> float:
        """Render one frame in the child; return its seconds as the child timed them."""
        return float(self._ask("frame")["seconds"])

    def _ask(self, command: str) -> dict:
        proc = self._proc
        try:
            proc.stdin.write(command + "\n")
            proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise DVRInputError(self._died()) from None
        return _reply(proc, self._died)

    def _died(self) -> str:
        code = self._proc.wait()
        why = f"signal {-code}" if code < 0 else f"exit code {code}"
        return f"VTK: the reference renderer's process ended ({why}); can VTK render here?"

    def close(self) -> None:
        """Ask the child for its peak memory and wait for it to end."""
        proc = self._proc
        try:
            if proc.poll() is None:
                self.peak_rss_mb = self._ask("quit").get("peak_rss_mb")
        except DVRInputError:
            pass
        finally:
            for pipe in (proc.stdin, proc.stdout):
                with contextlib.suppress(OSError):
                    pipe.close()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _reply(proc: subprocess.Popen, died) -> dict:
    line = proc.stdout.readline()
    if not line:
        raise DVRInputError(died())
    msg = json.loads(line)
    if "error" in msg:
        raise DVRInputError(msg["error"])
    return msg


@contextlib.contextmanager
def vtk_frame_process(volume: Volume, spec: StructureSpec, camera: Camera):
    """Yield a :class:`VTKFrames`: VTK's fixed-point frames rendered in a child process.

    The same frames as :func:`~dvr_perception.rays.vtk_reference.vtk_frame_timer` (the
    child runs it on the same volume, spec and camera); a renderer that cannot start or dies
    (no OpenGL here) raises :class:`~dvr_perception.errors.DVRInputError`.

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.structures.spec import Structure
    >>> vol = Volume(np.arange(8 ** 3, dtype=np.uint16).reshape(8, 8, 8) % 200)
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 1, 1), range=(50, 150)),))
    >>> cam = Camera.from_view(vol.bounds, width=16, height=16)
    >>> with vtk_frame_process(vol, spec, cam) as frame:  # doctest: +SKIP
    ...     frame() > 0
    True
    """
    with tempfile.TemporaryDirectory(prefix="dvr-perception-vtk-") as tmp:
        folder = Path(tmp)
        _write_inputs(folder, volume, spec, camera)
        cmd = [sys.executable, "-m", "dvr_perception.rays.vtk_process", str(folder)]
        proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            text=True, env=dict(os.environ),
        )  # fmt: skip
        frames = VTKFrames(proc)
        try:
            _reply(proc, frames._died)  # ready: loaded and rendered its set-up frame
            yield frames
        finally:
            frames.close()


def _write_inputs(folder: Path, volume: Volume, spec: StructureSpec, camera: Camera) -> None:
    """Write what the child renders into ``folder`` (:func:`_read_inputs` reads it back)."""
    from dvr_perception.structures.io import save_spec
    from dvr_perception.volume.io import save_volume

    save_volume(volume, folder / "volume.nhdr")
    if volume.labels is not None:
        save_volume(Volume(volume.labels, volume.spacing, volume.origin), folder / "labels.nhdr")
    save_spec(spec, folder / "spec.json")
    (folder / "camera.json").write_text(json.dumps(camera.to_dict()))


def _read_inputs(folder: Path) -> tuple[Volume, StructureSpec, Camera]:
    from dvr_perception.structures.io import load_spec
    from dvr_perception.volume.io import load_volume

    volume = load_volume(folder / "volume.nhdr")
    if (folder / "labels.nhdr").is_file():
        labels = load_volume(folder / "labels.nhdr").data
        volume = replace(volume, labels=labels)  # keeps direction and orientation
    spec = load_spec(folder / "spec.json")
    return volume, spec, Camera.from_dict(json.loads((folder / "camera.json").read_text()))


def _peak_mb() -> float | None:
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    m = re.search(r"VmHWM:\s+(\d+)\s*kB", status)
    return int(m.group(1)) / 1024 if m else None


def _serve(folder: Path) -> None:
    """Answer the parent: ``frame`` renders one frame, ``quit`` reports the peak memory."""
    from dvr_perception.rays.vtk_reference import vtk_frame_timer

    def say(msg: dict) -> None:
        sys.stdout.write(json.dumps(msg) + "\n")
        sys.stdout.flush()

    try:
        with vtk_frame_timer(*_read_inputs(folder)) as frame:
            say({"ready": True})
            for line in sys.stdin:
                if line.strip() == "frame":
                    say({"seconds": frame()})
                else:
                    break
    except DVRInputError as exc:
        say({"error": str(exc)})
        return
    say({"peak_rss_mb": _peak_mb()})


if __name__ == "__main__":
    _serve(Path(sys.argv[1]))
