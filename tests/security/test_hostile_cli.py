"""Hostile and careless inputs to the command line (issue 18).

Every case runs ``dvr-perception`` in a child process and must exit 2 within 10 s with one
``dvr-perception: error:`` line naming the file, field or option at fault, peak at less than
400 MB, and leave no file behind (the output folder stays empty).  To keep the suite fast the
cases run one after another in one child (:func:`run_batch`: the environment and the memory
limit are reset between calls, and each call's peak is bounded by the child's peak so far;
the few cases that render run in a child of their own).
"""

from __future__ import annotations

import gzip
import json
import os
import stat
import zlib
from pathlib import Path

import numpy as np
import pytest

GOOD_NRRD = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nendian: little\n"
SPEC = {
    "version": 1,
    "structures": [{"name": "a", "range": [10, 200], "importance": 0.5, "color": [1, 1, 1]}],
}
CAMERA = {"position": [0, 0, 400], "focal_point": [0, 0, 0], "view_up": [0, 1, 0]}


CASES: dict = {}


def case(*ids, params=None):
    """Register a case builder ``build(inputs, run[, param]) -> dict(argv, needles, ...)``."""

    def register(build):
        for i, name in enumerate(ids):
            CASES[name] = (build, None if params is None else params[i])
        return build

    return register


def _nhdr(folder: Path, body: str, name: str = "h.nhdr") -> Path:
    path = folder / name
    path.write_text(body)
    return path


def _render(volume, run: Path, *extra) -> list[str]:
    return ["render", str(volume), "--size", "16", "--out", str(run / "x.png"), *extra]


def _assert_nothing_written(run: Path) -> None:
    assert sorted(p.name for p in run.iterdir()) == []


def _gzip_bomb(folder: Path) -> Path:
    """An attached NRRD claiming 8x8x8 bytes whose gzip stream expands to 1 GiB (~1 MB)."""
    path = folder / "bomb.nrrd"
    comp = zlib.compressobj(1, zlib.DEFLATED, 31)  # gzip wrapper
    zeros = bytes(1 << 20)
    with open(path, "wb") as f:
        f.write((GOOD_NRRD + "encoding: gzip\n\n").encode())
        for _ in range(1024):
            f.write(comp.compress(zeros))
        f.write(comp.flush())
    assert path.stat().st_size < 8 << 20
    return path


# -- readers ---------------------------------------------------------------------------------


def _escape_case(inputs: Path, how: str) -> Path:
    outside = inputs.parent / "outside"
    outside.mkdir(exist_ok=True)
    (outside / "secret.bin").write_bytes(bytes(range(256)) * 2)
    vols = inputs / "vols"
    vols.mkdir(exist_ok=True)
    if how == "dotdot":
        name = "../../outside/secret.bin"
    elif how == "absolute":
        name = str(outside / "secret.bin")
    else:  # a symbolic link inside the folder pointing out of it
        (vols / "link.raw").symlink_to(outside / "secret.bin")
        name = "link.raw"
    return _nhdr(vols, GOOD_NRRD + f"encoding: raw\ndata file: {name}\n")


@case("escape-dotdot", "escape-absolute", "escape-symlink",
      params=["dotdot", "absolute", "symlink"])  # fmt: skip
def _escape(inputs, run, how):
    header = _escape_case(inputs, how)
    # nothing about the file (its size 512, whether it exists) may leak
    return {"argv": _render(header, run), "needles": [str(header), "'data file'", "outside"],
            "absent": ["512"]}  # fmt: skip


@case("allowed-root-option")
def _allowed_option(inputs, run):
    header = _escape_case(inputs, "dotdot")
    argv = [*_render(header, run), "--allow-data-root", inputs.parent / "outside"]
    return {"argv": argv, "code": 0, "written": ["x.png"]}


@case("allowed-root-env")
def _allowed_env(inputs, run):
    header = _escape_case(inputs, "dotdot")
    env = {"DVR_PERCEPTION_DATA_ROOTS": str(inputs.parent / "outside")}
    return {"argv": _render(header, run), "env": env, "code": 0, "written": ["x.png"]}


@case("data-file-fifo")
def _fifo(inputs, run):
    os.mkfifo(inputs / "pipe.raw")
    header = _nhdr(inputs, GOOD_NRRD + "encoding: raw\ndata file: pipe.raw\n")
    return {"argv": _render(header, run), "needles": [str(header), "not found"]}


@case("gzip-bomb")
def _bomb(inputs, run):
    bomb = _gzip_bomb(inputs)
    return {"argv": _render(bomb, run), "needles": [str(bomb), "more than the 512 bytes"]}


@case("gzip-claims-too-much")
def _claim(inputs, run):
    path = inputs / "claim.nrrd"
    body = GOOD_NRRD.replace("8 8 8", "1024 1024 512") + "encoding: gzip\n\n"
    path.write_bytes(body.encode() + gzip.compress(bytes(4096)))
    return {"argv": _render(path, run), "needles": [str(path), "cannot hold"]}


@case("sizes-above-int32", "sizes-product-overflows", "sizes-5000-digits",
      params=[("4294967296 4294967296 4294967296", "expected 0 to 2147483647"),
              ("2000000000 2000000000 2000000000", "more than the memory limit"),
              ("9" * 5000 + " 8 8", "too long")])  # fmt: skip
def _sizes(inputs, run, param):
    sizes, needle = param
    (inputs / "d.raw").write_bytes(bytes(512))
    header = _nhdr(inputs, GOOD_NRRD.replace("8 8 8", sizes) + "encoding: raw\ndata file: d.raw\n")
    return {"argv": _render(header, run), "needles": [str(header), "'sizes'", needle]}


@case("spacing-zero", "spacing-negative", "spacing-inf", "spacing-huge", "spacing-nan",
      "spacing-overflow", "spacing-5000-digits",
      params=[("spacings: 1 0 1", "'spacings'"), ("spacings: 1 -2 1", "'spacings'"),
              ("spacings: 1 inf 1", "'spacings'"), ("spacings: 1 1 1e7", "'spacings'"),
              ("space directions: (nan,0,0) (0,1,0) (0,0,1)", "'space directions'"),
              ("space directions: (1e300,0,0) (0,1e300,0) (0,0,1e300)", "'space directions'"),
              ("spacings: 1 1 " + "1" * 5000, "too long")])  # fmt: skip
def _spacing(inputs, run, param):
    field, needle = param
    (inputs / "d.raw").write_bytes(bytes(512))
    header = _nhdr(inputs, GOOD_NRRD + f"{field}\nencoding: raw\ndata file: d.raw\n")
    return {"argv": _render(header, run), "needles": [str(header), needle]}


@case("raw-size-before-reading")
def _sparse(inputs, run):
    with open(inputs / "big.raw", "wb") as f:  # sparse 8 GB: reading it whole would not fit
        f.truncate(8 << 30)
    header = _nhdr(inputs, GOOD_NRRD + "encoding: raw\ndata file: big.raw\n")
    return {"argv": _render(header, run), "needles": [str(header), "size mismatch"]}


MHD = "ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementType = MET_UCHAR\n"


@case("mhd-escape", "mhd-above-int32", "mhd-overflow", "mhd-5000-digits", "mhd-zero-spacing",
      "mhd-nan-spacing", "mhd-compression-ratio",
      params=[(MHD + "ElementDataFile = ../outside.raw\n", "outside"),
              (MHD.replace("8 8 8", "3000000000 8 8") + "ElementDataFile = d.raw\n", "'DimSize'"),
              (MHD.replace("8 8 8", "2000000000 2000000000 8") + "ElementDataFile = d.raw\n",
               "limit"),
              (MHD.replace("8 8 8", "8 8 " + "7" * 5000) + "ElementDataFile = d.raw\n",
               "too long"),
              (MHD + "ElementSpacing = 1 0 1\nElementDataFile = d.raw\n", "'ElementSpacing'"),
              (MHD + "ElementSpacing = 1 1 nan\nElementDataFile = d.raw\n", "'ElementSpacing'"),
              (MHD.replace("8 8 8", "800 800 800") + "CompressedData = True\n"
               "ElementDataFile = d.raw\n", "cannot hold")])  # fmt: skip
def _mhd(inputs, run, param):
    body, needle = param
    (inputs.parent / "outside.raw").write_bytes(bytes(512))
    (inputs / "d.raw").write_bytes(bytes(512))
    header = _nhdr(inputs, body, "h.mhd")
    return {"argv": _render(header, run), "needles": [str(header), needle]}


def _labelled(inputs: Path, labels: np.ndarray, dims=(32, 32, 32)) -> Path:
    """A volume of ``dims`` (x, y, z), the label volume ``labels`` and a spec naming both."""
    from dvr_perception.volume import Volume, save_volume

    ramp = np.linspace(0, 255, dims[0] * dims[1] * dims[2]).reshape(dims[::-1])
    save_volume(Volume(ramp.astype(np.uint8)), inputs / "v.nhdr")
    save_volume(Volume(labels), inputs / "labels.nhdr")
    spec = {"version": 1, "labels": "labels.nhdr", "structures": [
        {"name": "a", "label": 7, "importance": 0.8, "color": [1, 0, 0]},
        {"name": "b", "label": 30000, "importance": 0.4, "color": [0, 1, 0]}]}  # fmt: skip
    (inputs / "spec.json").write_text(json.dumps(spec))
    return inputs / "v.nhdr"


@case("labels-32768-distinct-values")
def _many_labels(inputs, run):
    # every voxel its own label: the work is per structure (two), never per distinct label
    labels = np.arange(32**3, dtype=np.int32).reshape(32, 32, 32)
    vol = _labelled(inputs, labels)
    argv = [*_render(vol, run), "--structures", inputs / "spec.json"]
    return {"argv": argv, "code": 0, "written": ["x.png"]}


@case("labels-other-dims", "labels-fractional", "labels-beyond-int32",
      params=[(np.zeros((8, 8, 8), np.int16), "do not match the volume's dims"),
              (np.full((32, 32, 32), 7.5, np.float32), "label values must be integers"),
              (np.full((32, 32, 32), 2.0**40, np.float64), "32-bit")])  # fmt: skip
def _bad_labels(inputs, run, param):
    labels, needle = param
    vol = _labelled(inputs, labels)
    argv = [*_render(vol, run), "--structures", inputs / "spec.json"]
    return {"argv": argv, "needles": ["labels.nhdr", needle]}


@case("volume-is-a-device")
def _device_volume(inputs, run):
    (inputs / "zero.nhdr").symlink_to("/dev/zero")
    return {"argv": _render(inputs / "zero.nhdr", run), "needles": ["zero.nhdr"]}


# -- resource limits -------------------------------------------------------------------------


@case("camera-width-1e9", "camera-height-1e308", "camera-16384-squared", "camera-inf-position",
      params=[({**CAMERA, "width": 10**9, "height": 8}, "width must be an integer in 1..16384"),
              ({**CAMERA, "width": 8, "height": 1e308}, "height"),
              ({**CAMERA, "width": 16384, "height": 16384}, "memory limit"),
              ({**CAMERA, "position": [1e400, 0, 0]}, "position")])  # fmt: skip
def _camera(inputs, run, param):
    camera, needle = param
    cam = inputs / "cam.json"
    cam.write_text(json.dumps(camera).replace("Infinity", "1e400"))
    argv = ["render", "phantom", "--camera", cam, "--out", run / "x.png", "--memory-limit", "256M"]
    return {"argv": argv, "needles": [f"--camera {cam}", needle]}


@case("size-over-memory-limit")
def _size(inputs, run):
    argv = [
        "render",
        "phantom",
        "--size",
        "16384",
        "--out",
        run / "x.png",
        "--memory-limit",
        "256M",
    ]
    return {"argv": argv, "needles": ["--size", "16384x16384", "--memory-limit"]}


@case("tiny-sample-distance")
def _tiny_step(inputs, run):
    spec = inputs / "tiny.json"
    spec.write_text(json.dumps({**SPEC, "rendering": {"sample_distance": 1e-9}}))
    argv = ["render", "phantom", "--structures", spec, "--size", "24", "--out", run / "x.png"]
    warning = "dvr-perception: warning: rendering.sample_distance 1e-09 is below 0.125"
    return {"argv": argv, "code": 0, "written": ["x.png"], "stderr": warning}


@case("100000-structures")
def _many(inputs, run):
    spec = inputs / "many.json"
    items = [
        {"name": f"s{i}", "range": [i, i + 0.5], "importance": 0.5, "color": [1, 1, 1]}
        for i in range(100_000)
    ]
    spec.write_text(json.dumps({"version": 1, "structures": items}))
    argv = ["render", "phantom", "--structures", spec, "--out", run / "x.png"]
    return {"argv": argv, "needles": ["many.json", "at most 32 structures, got 100000"]}


@case("views", "views-5000-digits", "resolution", "max-iter", "size-5000-digits",
      "memory-limit-5000-digits",
      params=[(["--views", "1000000"], "--views: expected 1 to 18"),
              (["--views", "9" * 5000], "--views"), (["--resolution", "100000"], "--resolution"),
              (["--max-iter", "10000000"], "--max-iter"), (["--size", "9" * 5000], "--size"),
              (["--memory-limit", "9" * 5000], "--memory-limit")])  # fmt: skip
def _options(inputs, run, param):
    extra, needle = param
    return {"argv": ["optimize", "phantom", "--out", run / "opt", *extra], "needles": [needle]}


@case("camera-is-dev-zero", "structures-is-dev-zero", params=["--camera", "--structures"])
def _dev_zero_json(inputs, run, which):
    argv = ["render", "phantom", which, "/dev/zero", "--out", run / "x.png"]
    return {"argv": argv, "needles": [which if which == "--camera" else "/dev/zero", "/dev/zero"]}


@case("spec-5000-digit-number")
def _digits_spec(inputs, run):
    spec = inputs / "digits.json"
    spec.write_text(json.dumps(SPEC).replace("0.5", "1" + "0" * 5000))
    argv = ["render", "phantom", "--structures", spec, "--out", run / "x.png"]
    return {"argv": argv, "needles": ["digits.json"]}


# -- outputs ---------------------------------------------------------------------------------


@case("out-is-dev-null")
def _dev_null(inputs, run):
    argv = ["render", "phantom", "--out", "/dev/null"]
    return {"argv": argv, "needles": ["/dev/null", "regular"]}


@case("out-is-a-fifo")
def _fifo_out(inputs, run):
    os.mkfifo(run / "pipe.png")
    return {"argv": ["render", "phantom", "--out", run / "pipe.png"], "needles": ["pipe.png"],
            "written": ["pipe.png"]}  # fmt: skip


@case("out-is-a-directory")
def _dir_out(inputs, run):
    (run / "dir.png").mkdir()
    return {"argv": ["render", "phantom", "--out", run / "dir.png"],
            "needles": ["dir.png", "is a directory"], "written": ["dir.png"]}  # fmt: skip


@case("out-and-buffers-one-path")
def _same(inputs, run):
    argv = ["render", "phantom", "--out", run / "x.png", "--buffers", f"{run}/./x.png"]
    return {"argv": argv, "needles": ["--buffers", "the same file as --out"]}


def _unwritable() -> Path | None:
    """A folder no file can be created in, even by root (``/sys``); None if there is none."""
    folder = Path("/sys")
    try:
        with open(folder / ".probe", "w"):
            pass
    except OSError:
        return folder
    return None


@case("out-folder-unwritable", "out-dir-unwritable", params=["render", "measure"])
def _unwritable_case(inputs, run, command):
    folder = _unwritable() if os.geteuid() == 0 else inputs / "ro"
    if folder is None:
        pytest.skip("no unwritable folder on this machine")
    if os.geteuid() != 0:
        folder.mkdir()
        folder.chmod(0o555)
    out = ["--out", folder / "x.png"] if command == "render" else ["--out-dir", folder]
    return {"argv": [command, "phantom", "--size", "16", *out],
            "needles": [f"output folder {folder}", "cannot write"],
            "absent": [".tmp", "vtk", "libpng"]}  # fmt: skip


@case("out-dir-locked")
def _locked(inputs, run):
    (run / "m").mkdir()
    (run / "m" / ".dvr-perception.lock").write_text("12345\n")
    argv = ["measure", "phantom", "--size", "16", "--out-dir", run / "m"]
    return {"argv": argv, "needles": [f"output folder {run / 'm'}", "another dvr-perception run",
            "12345"], "written": ["m"], "lock": run / "m" / ".dvr-perception.lock"}  # fmt: skip


# -- running ---------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def results(tmp_path_factory, batch):
    """Build every case, run them all in one child, return ``{id: (case, Run, run folder)}``."""
    import fcntl

    root = tmp_path_factory.mktemp("hostile")
    built, calls, held = {}, [], []
    for name, (build, param) in CASES.items():
        inputs, run = root / name / "in", root / name / "run"
        inputs.mkdir(parents=True)
        run.mkdir()
        try:
            spec = build(inputs, run) if param is None else build(inputs, run, param)
        except pytest.skip.Exception:
            continue
        if "lock" in spec:  # held by this process while the child runs
            fh = open(spec["lock"], "a")  # noqa: SIM115
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(fh)
        built[name] = (spec, run)
        calls.append({"argv": spec["argv"], "env": spec.get("env", {}), "cwd": str(run),
                      "alone": spec.get("code", 2) != 2})  # fmt: skip
    null_before = os.stat("/dev/null")
    try:
        runs = batch(calls, root)
    finally:
        for fh in held:
            fh.close()
    null_after = os.stat("/dev/null")
    assert stat.S_ISCHR(null_after.st_mode)
    assert (null_after.st_ino, null_after.st_rdev) == (null_before.st_ino, null_before.st_rdev)
    return {name: (*built[name], r) for name, r in zip(built, runs, strict=True)}


@pytest.mark.parametrize("name", list(CASES))
def test_hostile_input(results, name):
    if name not in results:
        pytest.skip("case not built on this machine")
    spec, run, result = results[name]
    if spec.get("code", 2) == 2:
        line = result.one_error(*spec.get("needles", []))
        for text in spec.get("absent", []):
            assert text not in line.lower(), line
    else:
        assert result.code == spec["code"], result.stderr
        result.bounded()
        if "stderr" in spec:
            lines = [ln for ln in result.stderr.splitlines() if spec["stderr"] in ln]
            assert len(lines) == 1, result.stderr
    # nothing else written: no output, no temporary, no lock, no staging folder
    assert sorted(p.name for p in run.iterdir()) == sorted(spec.get("written", []))
    if "lock" in spec:
        assert sorted(p.name for p in spec["lock"].parent.iterdir()) == [".dvr-perception.lock"]


def test_every_class_of_issue_18_is_covered():
    names = " ".join(CASES)
    for needle in ("escape", "gzip-bomb", "sizes-product-overflows", "spacing-nan", "mhd",
                   "camera-width", "views", "structures", "sample-distance", "dev-null",
                   "one-path", "unwritable", "locked", "labels"):  # fmt: skip
        assert needle in names, needle
