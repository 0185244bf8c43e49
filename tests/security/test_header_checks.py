"""Issue 29 from the attacker's side: the header check and the read are one parse.

Every hostile header of :mod:`hostile_headers` is refused with one error naming the file and
the field through :func:`load_volume`, ``dvr-perception measure`` (one line, exit 2, bounded
time and memory, under ``--memory-limit 64M``) and the web app's upload check (under a small
``--max-volume-mb``).  The hypothesis tests write MetaImage, legacy VTK and ``.vti`` headers
with keys in random case, repeated keys, comments and white space, and check that what the
check sized is exactly what the reader loaded (or that both refused), and that a file outside
the volume's folder is never read.
"""

from __future__ import annotations

import importlib.util
import tempfile
import tracemalloc
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dvr_perception._vtk import vtkNIFTIImageWriter
from dvr_perception.app.uploads import check_volume_bytes
from dvr_perception.errors import DVRInputError
from dvr_perception.rays import memory
from dvr_perception.volume import Volume, load_volume
from dvr_perception.volume.convert import to_vtk_image
from dvr_perception.volume.io import check_volume_file, header_axes

_spec = importlib.util.spec_from_file_location(
    "hostile_headers", Path(__file__).with_name("hostile_headers.py")
)
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)

LIMIT = "64M"


@pytest.fixture(autouse=True)
def small_memory_limit():
    memory.set_limit(LIMIT)
    yield
    memory.set_limit(None)


def _folder(tmp_path: Path) -> Path:
    folder = tmp_path / "vol"
    folder.mkdir()
    H.write_secret(folder)
    return folder


@pytest.mark.parametrize("name", list(H.CASES))
def test_load_volume_refuses_each_case_naming_file_and_field(tmp_path, name):
    path, needles = H.CASES[name](_folder(tmp_path))
    tracemalloc.start()
    try:
        with pytest.raises(DVRInputError) as info:
            load_volume(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, (needle, msg)
    assert peak < 40 * 2**20, peak  # never the claimed sizes, never a decompressed bomb
    # the same parse serves the header-only check (uploads, ParaView's MPI ranks, pvbatch);
    # a case it passes (a bomb, truncated compressed data) is refused on reading, as above
    for check in (check_volume_file, header_axes):
        try:
            check(path)
        except DVRInputError as exc:
            assert str(exc).startswith(str(path)), exc  # noqa: PT017


@pytest.mark.parametrize("name", list(H.CASES))
def test_the_upload_check_refuses_each_case(tmp_path, name):
    path, _ = H.CASES[name](_folder(tmp_path))
    upload = path.name.replace(".mhd", ".mha")
    try:
        check_volume_bytes(upload, path.read_bytes(), max_volume_bytes=1_000_000)
    except DVRInputError as exc:
        msg = str(exc)
        assert msg.startswith(f"upload {upload}: "), msg
        assert "\n" not in msg
        return
    # passed the header check (a case only the full read refuses): the app then loads it
    # with load_volume, which must refuse it
    with pytest.raises(DVRInputError):
        load_volume(path)


def test_the_upload_check_names_the_field_and_the_upload_limit(tmp_path):
    path, _ = H.vti_many_arrays(_folder(tmp_path), count=2, edge=48)
    with pytest.raises(DVRInputError, match=r"upload many\.vti: field 'WholeExtent'.*"
                       r"\(2 arrays\).*--max-volume-mb"):  # fmt: skip
        check_volume_bytes("many.vti", path.read_bytes(), max_volume_bytes=1_000_000)
    # one such array fits; the two VTK would allocate do not
    check_volume_bytes("many.vti", path.read_bytes(), max_volume_bytes=2 * 48**3 * 8)


def test_the_app_never_keeps_nor_loads_a_hostile_upload(tmp_path):
    from dvr_perception.app.session import Session

    folder = _folder(tmp_path)
    session = Session(None, tmp_path / "exports", state_dir=tmp_path / "state",
                      max_volume_bytes=1_000_000)  # fmt: skip
    for build in H.CASES.values():
        path, _ = build(folder)
        name = path.name.replace(".mhd", ".mha")
        with pytest.raises(DVRInputError, match=f"upload {name}"):
            session.store_upload(name, path.read_bytes())
    uploads = tmp_path / "state" / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())


def test_the_data_after_a_local_header_is_data_not_header(tmp_path):
    # LOCAL first: the bytes after it are voxels, even when they read like a header line
    folder = _folder(tmp_path)
    tail = b"ElementDataFile = ../secret.bin\n"
    body = tail + bytes(64 - len(tail))
    path = folder / "t.mha"
    path.write_bytes(H.META.encode() + b"ElementDataFile = LOCAL\n" + body)
    vol = load_volume(path)
    assert vol.data.tobytes() == body
    assert H.SECRET[:32] not in vol.data.tobytes()


def test_header_size_picks_the_offset_inside_an_allowed_data_file(tmp_path):
    folder = _folder(tmp_path)
    (folder / "d.raw").write_bytes(b"JUNK" + bytes(range(64)))
    path = folder / "h.mhd"
    path.write_text(H.META + "HeaderSize = 4\nElementDataFile = d.raw\n")
    assert load_volume(path).data.ravel().tolist() == list(range(64))
    path.write_text(H.META + "HeaderSize = -1\nElementDataFile = d.raw\n")
    assert load_volume(path).data.ravel().tolist() == list(range(64))
    path.write_text(H.META + "HeaderSize = 5\nElementDataFile = d.raw\n")
    with pytest.raises(DVRInputError, match=r"h\.mhd \(data file d\.raw\): truncated"):
        load_volume(path)


def test_many_arrays_load_the_scalars_when_they_fit(tmp_path):
    path, _ = H.vti_many_arrays(_folder(tmp_path), count=3, edge=8)
    vol = load_volume(path)
    assert vol.dims == (8, 8, 8)
    assert vol.data.dtype == np.float64
    assert not vol.data.any()


def test_nifti2_reads_as_nifti1_and_both_are_checked(tmp_path):
    vol = Volume(np.arange(60, dtype=np.int16).reshape(3, 4, 5), spacing=(1, 2, 3),
                 origin=(4, 5, 6))  # fmt: skip
    for version in (1, 2):
        writer = vtkNIFTIImageWriter()
        writer.SetNIFTIVersion(version)
        writer.SetInputData(to_vtk_image(vol))
        writer.SetFileName(str(tmp_path / f"v{version}.nii"))
        writer.Write()
    assert (tmp_path / "v2.nii").read_bytes()[:4] == (540).to_bytes(4, "little")
    one, two = load_volume(tmp_path / "v1.nii"), load_volume(tmp_path / "v2.nii")
    np.testing.assert_array_equal(one.data, two.data)
    assert (one.spacing, one.origin) == (two.spacing, two.origin)
    assert sorted(one.data.ravel().tolist()) == list(range(60))
    assert check_volume_file(tmp_path / "v2.nii")[:2] == ((5, 4, 3), np.dtype("<i2"))
    blob = (tmp_path / "v2.nii").read_bytes()
    (tmp_path / "t2.nii").write_bytes(blob[:-10])
    with pytest.raises(DVRInputError, match=r"t2\.nii: truncated"):
        load_volume(tmp_path / "t2.nii")


@pytest.mark.parametrize("mode", ["appended-raw", "appended-base64", "binary"])
@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("header", ["UInt32", "UInt64"])
def test_every_vti_encoding_loads_and_every_truncation_is_refused(tmp_path, mode, compressed,
                                                                  header):  # fmt: skip
    from dvr_perception._vtk import vtkXMLImageDataWriter

    rng = np.random.default_rng(1)
    vol = Volume(rng.integers(-999, 999, (5, 6, 7)).astype(np.int32), spacing=(1, 2, 3))
    writer = vtkXMLImageDataWriter()
    writer.SetInputData(to_vtk_image(vol))
    writer.SetDataMode(1 if mode == "binary" else 2)
    writer.SetEncodeAppendedData(mode == "appended-base64")
    if not compressed:
        writer.SetCompressorTypeToNone()
    else:
        writer.SetBlockSize(256)  # several blocks
    writer.SetHeaderTypeToUInt32() if header == "UInt32" else writer.SetHeaderTypeToUInt64()
    path = tmp_path / "v.vti"
    writer.SetFileName(str(path))
    writer.Write()
    np.testing.assert_array_equal(load_volume(path).data, vol.data)
    blob = path.read_bytes()
    cut = blob.rindex(b"</AppendedData>" if mode != "binary" else b"</DataArray>")
    end = len(blob[:cut].rstrip())  # the last data byte (or base64 character)
    for drop in (1, 7, 60):  # data bytes (or base64 characters) missing
        short = tmp_path / f"s{drop}.vti"
        short.write_bytes(blob[: end - drop] + blob[end:])
        with pytest.raises(DVRInputError, match=rf"s{drop}\.vti: .*(truncated|malformed)"):
            load_volume(short)


# -- the command line ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_results(tmp_path_factory, batch):
    root = tmp_path_factory.mktemp("issue29")
    calls, built = [], {}
    for name, build in H.CASES.items():
        folder = root / name / "vol"
        folder.mkdir(parents=True)
        H.write_secret(folder)
        path, needles = build(folder)
        run = root / name / "run"
        run.mkdir()
        built[name] = (path, needles, run)
        argv = ["measure", str(path), "--size", "16", "--memory-limit", LIMIT]
        calls.append({"argv": argv, "cwd": str(run)})
    runs = batch(calls, root)
    return {name: (*built[name], r) for name, r in zip(built, runs, strict=True)}


@pytest.mark.parametrize("name", list(H.CASES))
def test_measure_gives_one_error_line(cli_results, name):
    path, needles, run, result = cli_results[name]
    line = result.one_error(str(path), *needles)
    assert "Traceback" not in result.stderr
    assert "secret" not in line or "../secret.bin" in line  # named as written, never read
    assert sorted(run.iterdir()) == []


# -- hypothesis: keys in any case, repeated keys, comments, white space ----------------------

FUZZ = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _cased(draw, key: str) -> str:
    flips = draw(st.lists(st.booleans(), min_size=len(key), max_size=len(key)))
    mode = draw(st.sampled_from(["as is", "as is", "random", "lower", "upper"]))
    if mode == "as is":
        return key
    if mode == "lower":
        return key.lower()
    if mode == "upper":
        return key.upper()
    return "".join(c.swapcase() if f else c for c, f in zip(key, flips, strict=True))


_SPACE = st.sampled_from(["", " ", "  ", "\t", " \t "])


@st.composite
def meta_files(draw):
    """A MetaImage header (fields in random case, repeated, reordered) and its data."""
    small, big = "2 3 4", draw(st.sampled_from(["2 3 4", "40 40 40", "1000 1000 1000"]))
    fields = [
        ("NDims", "3"),
        ("DimSize", small),
        ("ElementType", draw(st.sampled_from(["MET_UCHAR", "MET_SHORT", "MET_FLOAT"]))),
    ]
    extras = [("DimSize", big), ("ElementSpacing", "1 1 2"), ("Offset", "1 2 3"),
              ("Origin", "3 2 1"), ("CompressedData", "True"), ("HeaderSize", "8"),
              ("ElementDataFile", "../secret.bin"), ("TransformMatrix", "0 1 0 1 0 0 0 0 1"),
              ("ElementNumberOfChannels", "1"), ("Comment", "ElementDataFile = ../secret.bin"),
              ("ElementByteOrderMSB", "True")]  # fmt: skip
    fields += draw(st.lists(st.sampled_from(extras), max_size=3))
    fields = draw(st.permutations(fields))
    lines = [f"{draw(_SPACE)}{_cased(draw, k)}{draw(_SPACE)}={draw(_SPACE)}{v}" for k, v in fields]
    end = draw(st.sampled_from(["LOCAL", "d.raw", "../secret.bin", "sub/../d.raw"]))
    lines.append(f"{_cased(draw, 'ElementDataFile')} = {end}")
    data = draw(st.sampled_from([bytes(96), bytes(range(96)), bytes(40)]))
    return "\n".join(lines) + "\n", data, ".mha" if end == "LOCAL" else ".mhd"


@st.composite
def legacy_files(draw):
    """A legacy VTK header with keywords in random case, repeated, with blank lines."""
    lines = ["# vtk DataFile Version 3.0", "title", _cased(draw, "BINARY"),
             f"{_cased(draw, 'DATASET')} {_cased(draw, 'STRUCTURED_POINTS')}"]  # fmt: skip
    body = [("DIMENSIONS", "2 3 4"), ("SPACING", "1 1 2"), ("ORIGIN", "0 0 0")]
    extra = [("DIMENSIONS", "100 100 100"), ("ASPECT_RATIO", "1 1 1"), ("FIELD", "f 0")]
    body += draw(st.lists(st.sampled_from(extra), max_size=1)) if draw(st.booleans()) else []
    for key, value in draw(st.permutations(body)):
        lines += [""] * draw(st.integers(0, 2)) + [f"{_cased(draw, key)}{draw(_SPACE)} {value}"]
    kind = draw(st.sampled_from(["short", "float", "double", "bit"]))
    count = draw(st.sampled_from(["24", "24", "24", "1000000"]))
    lines += [f"{_cased(draw, 'POINT_DATA')} {count}", f"{_cased(draw, 'SCALARS')} s {kind}",
              f"{_cased(draw, 'LOOKUP_TABLE')} default"]  # fmt: skip
    size = 24 * {"short": 2, "float": 4, "double": 8, "bit": 1}[kind]
    data = bytes(range(256))[: draw(st.sampled_from([size, size, size, size - 8, 40]))]
    tail = draw(st.sampled_from([b"", b"\n", b"\n", b"\nDIMENSIONS 9 9 9\n"]))
    return "\n".join(lines) + "\n", data + tail, ".vtk"


@st.composite
def vti_files(draw):
    """A ``.vti`` with comments, white space in tags, repeated and extra arrays."""
    import struct

    ext = draw(st.sampled_from(["0 1 0 2 0 3", "0 1 0 2 0 3", "0 1 0 2 0 3", "0 39 0 39 0 39"]))
    lead = draw(st.sampled_from(["", "", "\n  ", "<!-- x -->",
                                 '<!-- <ImageData WholeExtent="0 1 0 1 0 1"> -->']))  # fmt: skip
    space = draw(st.sampled_from([" ", "\n", " \t\n "]))
    comp = draw(
        st.sampled_from(["", "", f'{space}compressor{space}={space}"vtkZLibDataCompressor"'])
    )
    n = draw(st.integers(1, 4))
    kind = draw(st.sampled_from(["UInt8", "Int16", "Float64"]))
    arrays = "".join(
        f'<DataArray{space}type="{kind}" Name="{"s" if i == 0 else f"a{i}"}"{space}'
        f'format="appended" offset="0"/>'
        for i in range(n)
    )
    inner = draw(st.sampled_from(["", "", "", "<!-- in -->"]))
    head = (f'{lead}<VTKFile type="ImageData" byte_order="LittleEndian"{comp}>'
            f'<ImageData WholeExtent="{ext}" Spacing="1 1 1">{inner}<Piece Extent="{ext}">'
            f'<PointData Scalars="s">{arrays}</PointData></Piece></ImageData>'
            '<AppendedData encoding="raw">_')  # fmt: skip
    nbytes = 24 * np.dtype(kind.lower().replace("uint8", "u1").replace("int16", "i2")).itemsize
    size = draw(st.sampled_from([nbytes, nbytes, nbytes, nbytes - 8, 64000 * 8]))
    data = struct.pack("<I", size) + bytes(range(256)) * (nbytes // 256 + 1)
    data = data[: 4 + draw(st.sampled_from([nbytes, nbytes, nbytes, nbytes // 2]))]
    return head, data + b"</AppendedData></VTKFile>", ".vti"


def _check_then_read(text, data: bytes, ext: str) -> str:
    """The check sizes exactly what the reader loads, or both refuse; nothing outside read."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "vol"
        (folder / "sub").mkdir(parents=True)
        H.write_secret(folder)
        (folder / "d.raw").write_bytes(data)
        path = folder / f"h{ext}"
        blob = text.encode("latin-1") if isinstance(text, str) else text
        path.write_bytes(blob + (data if ext in (".mha", ".vtk", ".vti") else b""))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                dims, dtype, src = check_volume_file(path)
            except DVRInputError as exc:
                assert str(exc).startswith(str(path)), exc  # noqa: PT017
                with pytest.raises(DVRInputError):
                    load_volume(path)
                return "refused by the check"
            assert src is not None
            assert folder in src.resolve().parents
            try:
                vol = load_volume(path)
            except DVRInputError as exc:  # the data itself (truncated, non-finite): named
                assert str(exc).startswith(str(path)), exc  # noqa: PT017
                return "refused on reading"
        assert vol.data.size == int(np.prod(dims))
        assert vol.data.dtype == dtype.newbyteorder("=")
        assert H.SECRET[:16] not in vol.data.tobytes()
    return "loaded"


def _agree(strategy) -> Counter:
    outcomes: Counter = Counter()

    @FUZZ
    @given(strategy)
    def run(case):
        outcomes[_check_then_read(*case)] += 1

    run()
    return outcomes


@pytest.mark.parametrize("strategy", [meta_files, legacy_files, vti_files])
def test_check_and_read_agree(strategy):
    outcomes = _agree(strategy())
    # not vacuous: the strategies reach files that load and files refused either way
    assert outcomes["loaded"] >= 3, outcomes
    assert outcomes["refused by the check"] >= 10, outcomes


# -- the other front ends: ParaView's reader, pvbatch's MPI path, the app's data folder -----


@pytest.mark.parametrize("name", ["meta_key_case", "vti_comment_before_root",
                                  "legacy_later_dimensions", "nifti2_huge"])  # fmt: skip
def test_the_paraview_reader_reports_one_error(tmp_path, name):
    from dvr_perception.filters import VolumeReader

    path, needles = H.CASES[name](_folder(tmp_path))
    reader = VolumeReader()
    reader.file_name = str(path)
    assert not reader.Update()
    assert reader.error_message.startswith(str(path)), reader.error_message
    for needle in needles:
        assert needle in reader.error_message


@pytest.mark.parametrize("name", ["meta_key_case", "meta_repeated_dims", "vti_many_arrays",
                                  "legacy_later_dimensions"])  # fmt: skip
def test_pvbatch_ranks_refuse_a_header_their_paraview_readers_would_read_otherwise(tmp_path,
                                                                                 name):  # fmt: skip
    from dvr_perception.cli.pvbatch import _check_file_order

    path, needles = H.CASES[name](_folder(tmp_path))
    with pytest.raises(DVRInputError) as info:
        _check_file_order(str(path))
    assert str(info.value).startswith(str(path))
    assert needles[0] in str(info.value)


def test_the_app_data_folder_refuses_a_hostile_volume(tmp_path):
    from dvr_perception.app.session import Session

    folder = _folder(tmp_path)
    path, _ = H.meta_key_case(folder)
    session = Session(folder, tmp_path / "exports", state_dir=tmp_path / "state")
    assert path.name in session.volume_choices()
    with pytest.raises(DVRInputError, match="case-sensitive"):
        session.load_volume(path.name)
