"""Property-based fuzzing of the untrusted inputs: volume headers, spec JSON, camera JSON.

Whatever the input, the parsers either succeed or raise one
:class:`~dvr_perception.errors.DVRInputError`; never another exception, and every example
finishes within the deadline (bounded time; the memory limit is 64 MB, so nothing large is
allocated).  The runs are bounded (``max_examples``) and derandomised so CI is reproducible.
"""

from __future__ import annotations

import bz2
import gzip
import json
import tempfile
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dvr_perception.errors import DVRInputError
from dvr_perception.rays import memory
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.io import load_spec, spec_from_dict
from dvr_perception.volume import Volume
from dvr_perception.volume.io import load_volume

FUZZ = settings(
    max_examples=100,
    deadline=2000,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


@pytest.fixture(autouse=True, scope="module")
def small_memory_limit():
    memory.set_limit("64M")
    yield
    memory.set_limit(None)


def _outcome(call):
    """Run ``call``; return "ok" or "error" (a DVRInputError); anything else fails the test."""
    message = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            call()
        except DVRInputError as exc:
            message = str(exc)
    if message is None:
        return "ok"
    assert message.strip(), "an error must say what is wrong"
    assert "Traceback" not in message
    return "error"


# -- values ----------------------------------------------------------------------------------

NUMBERS = st.one_of(
    st.integers(-(10**30), 10**30).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "-1", "1e308", "1e-320", "nan", "inf", "-inf", "9" * 5000, "", " "]),
)
TEXT = st.text(st.characters(blacklist_characters="\n\r", blacklist_categories=("Cs",)),
               max_size=40)  # fmt: skip
VALUE = st.one_of(NUMBERS, TEXT, st.lists(NUMBERS, max_size=4).map(" ".join))


def _tuple(n: int):
    return st.lists(NUMBERS, min_size=n, max_size=n).map(" ".join)


# -- NRRD ------------------------------------------------------------------------------------

NRRD_FIELDS = {
    "type": st.one_of(st.sampled_from(["uint8", "short", "float", "double", "block"]), TEXT),
    "dimension": st.one_of(st.just("3"), VALUE),
    "sizes": st.one_of(st.just("8 8 8"), st.just("4 8 16"), _tuple(3), VALUE),
    "encoding": st.sampled_from(["raw", "gzip", "bzip2", "hex", "ascii", "", "RAW"]),
    "endian": st.sampled_from(["little", "big", "middle"]),
    "spacings": st.one_of(_tuple(3), VALUE),
    "space directions": st.one_of(
        st.lists(
            _tuple(3).map(lambda t: "(" + t.replace(" ", ",") + ")"), min_size=3, max_size=3
        ).map(" ".join),
        VALUE,
    ),
    "space origin": st.one_of(_tuple(3).map(lambda t: "(" + t.replace(" ", ",") + ")"), VALUE),
    "data file": st.sampled_from(
        ["d.raw", "../d.raw", "/etc/passwd", "LIST", "d%03d.raw", "missing.raw", "", "."]
    ),
    "byte skip": st.sampled_from(["0", "1", "-1"]),
}


NRRD_VALID = {"type": "uint8", "dimension": "3", "sizes": "8 8 8", "encoding": "raw",
              "endian": "little", "data file": "d.raw"}  # fmt: skip


@st.composite
def nrrd_headers(draw):
    """A valid detached header with a few fields replaced, dropped or added (reaches deep)."""
    fields = dict(NRRD_VALID)
    for key in draw(st.lists(st.sampled_from(sorted(NRRD_FIELDS)), unique=True, max_size=3)):
        fields[key] = draw(NRRD_FIELDS[key])
    for key in draw(st.lists(st.sampled_from(sorted(fields)), unique=True, max_size=1)):
        del fields[key]
    lines = [f"{k}: {v}" for k, v in fields.items()]
    if draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), draw(TEXT))  # a stray line
    return "NRRD0004\n" + "\n".join(lines) + "\n"


@FUZZ
@given(
    header=nrrd_headers(),
    data=st.one_of(st.binary(min_size=512, max_size=512), st.binary(max_size=600)),
)
def test_nrrd_header_fuzz(header, data):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "vol"
        folder.mkdir()
        (folder / "d.raw").write_bytes(data)
        (Path(tmp) / "d.raw").write_bytes(data)
        path = folder / "h.nhdr"
        path.write_bytes(header.encode("utf-8", "surrogatepass"))
        _outcome(lambda: load_volume(path))


@FUZZ
@given(encoding=st.sampled_from(["gzip", "bzip2"]), sizes=_tuple(3) | st.just("8 8 8"),
       payload=st.binary(max_size=700), packed=st.booleans(), cut=st.integers(0, 64),
       junk=st.binary(max_size=16))  # fmt: skip
def test_compressed_nrrd_fuzz(encoding, sizes, payload, packed, cut, junk):
    """Valid, truncated, padded and garbage gzip/bzip2 streams against arbitrary sizes."""
    if packed:
        payload = (gzip.compress if encoding == "gzip" else bz2.compress)(payload)
        payload = payload[: len(payload) - cut] + junk
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.nrrd"
        head = f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {sizes}\nencoding: {encoding}\n\n"
        path.write_bytes(head.encode() + payload)
        _outcome(lambda: load_volume(path))


@FUZZ
@given(blob=st.binary(max_size=400))
def test_attached_nrrd_bytes_fuzz(blob):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "a.nrrd"
        path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\n" + blob)
        _outcome(lambda: load_volume(path))


# -- MetaImage -------------------------------------------------------------------------------

MHD_FIELDS = {
    "NDims": st.one_of(st.just("3"), VALUE),
    "DimSize": st.one_of(st.just("8 8 8"), st.just("2 4 8"), _tuple(3), VALUE),
    "ElementType": st.one_of(
        st.sampled_from(["MET_UCHAR", "MET_SHORT", "MET_FLOAT", "MET_X"]), TEXT
    ),
    "ElementSpacing": st.one_of(_tuple(3), VALUE),
    "Offset": st.one_of(_tuple(3), VALUE),
    "ElementNumberOfChannels": st.one_of(st.sampled_from(["1", "3", "0"]), VALUE),
    "CompressedData": st.sampled_from(["True", "False"]),
    "HeaderSize": st.sampled_from(["0", "-1", "4", "99999"]),
}


MHD_VALID = {"NDims": "3", "DimSize": "8 8 8", "ElementType": "MET_UCHAR"}


@st.composite
def mhd_headers(draw):
    """A valid MetaImage header with a few fields replaced, dropped or added."""
    fields = dict(MHD_VALID)
    for key in draw(st.lists(st.sampled_from(sorted(MHD_FIELDS)), unique=True, max_size=3)):
        fields[key] = draw(MHD_FIELDS[key])
    for key in draw(st.lists(st.sampled_from(sorted(fields)), unique=True, max_size=1)):
        del fields[key]
    lines = ["ObjectType = Image"] + [f"{k} = {v}" for k, v in fields.items()]
    lines.append(
        "ElementDataFile = "
        + draw(st.sampled_from(["d.raw", "d.raw", "../d.raw", "/etc/passwd", "LOCAL", "x.raw"]))
    )
    return "\n".join(lines) + "\n"


@FUZZ
@given(
    header=mhd_headers(),
    data=st.one_of(st.binary(min_size=512, max_size=512), st.binary(max_size=600)),
)
def test_metaimage_header_fuzz(header, data):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "vol"
        folder.mkdir()
        (folder / "d.raw").write_bytes(data)
        (Path(tmp) / "d.raw").write_bytes(data)
        path = folder / "h.mhd"
        path.write_bytes(header.encode("utf-8", "surrogatepass"))
        _outcome(lambda: load_volume(path))


# -- spec JSON -------------------------------------------------------------------------------

JSON = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(10**40), 10**40),
              st.floats(allow_nan=True, allow_infinity=True), TEXT),
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.dictionaries(TEXT, inner, max_size=4)),
    max_leaves=12,
)  # fmt: skip
GOOD_SPEC = {
    "version": 1,
    "background": [0, 0, 0],
    "structures": [
        {"name": "a", "range": [0, 10], "importance": 0.5, "color": [1, 0, 0], "edge": 0.1,
         "lighting": {"ambient": 0.2, "diffuse": 0.8, "specular": 0.2, "specular_power": 16}},
        {"name": "b", "label": 3, "importance": 1.0, "color": [0, 1, 0], "opacity": 0.2},
    ],
    "rendering": {"shade": True, "sample_distance": 0.5, "light_direction": [0, 0, 1]},
    "view": [30, 20, 1.0],
    "labels": "labels.nhdr",
}  # fmt: skip


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*prefix, i))


SPEC_PATHS = [p for p in _paths(GOOD_SPEC) if p]


def _mutate(doc, path, value):
    doc = json.loads(json.dumps(doc))
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


@FUZZ
@given(path=st.sampled_from(SPEC_PATHS), value=JSON)
def test_spec_field_fuzz(path, value):
    _outcome(lambda: spec_from_dict(_mutate(GOOD_SPEC, path, value)))


@FUZZ
@given(doc=JSON)
def test_spec_document_fuzz(doc):
    _outcome(lambda: spec_from_dict(doc))


@FUZZ
@given(
    text=st.one_of(
        JSON.map(lambda d: json.dumps(d)),
        st.text(max_size=200),
        st.sampled_from(["[" * 100000, '{"version": 1' + "0" * 5000 + "}"]),
    )
)
def test_spec_file_fuzz(text):  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.json"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        _outcome(lambda: load_spec(path))


# -- camera JSON -----------------------------------------------------------------------------

CAMERA_VALUES = {
    "position": st.one_of(st.lists(JSON, max_size=4), JSON),
    "focal_point": st.one_of(st.lists(st.floats(), min_size=3, max_size=3), JSON),
    "view_up": st.one_of(st.lists(st.floats(), min_size=3, max_size=3), JSON),
    "view_angle": JSON,
    "parallel_projection": JSON,
    "parallel_scale": JSON,
    "width": st.one_of(st.integers(-(10**30), 10**30), JSON),
    "height": st.one_of(st.integers(-(10**30), 10**30), st.floats(), JSON),
}


@FUZZ
@given(fields=st.dictionaries(st.sampled_from(sorted(CAMERA_VALUES)), st.none(), max_size=8),
       data=st.data())  # fmt: skip
def test_camera_json_fuzz(fields, data):
    d = {k: data.draw(CAMERA_VALUES[k]) for k in fields}
    if data.draw(st.booleans()):
        d[data.draw(TEXT)] = data.draw(JSON)
    if _outcome(lambda: Camera.from_dict(d)) == "ok":
        cam = Camera.from_dict(d)
        assert 1 <= cam.width <= 16384
        assert 1 <= cam.height <= 16384


def test_fuzz_finds_successes_too():
    """The strategies reach valid inputs, so the properties are not vacuous."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "h.nhdr"
        (Path(tmp) / "d.raw").write_bytes(bytes(range(256)) * 2)
        path.write_text("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n"
                        "data file: d.raw\n")  # fmt: skip
        assert isinstance(load_volume(path), Volume)
    doc = _mutate(GOOD_SPEC, ("structures", 0, "importance"), 0.25)
    assert spec_from_dict(doc).structures[0].importance == 0.25
    assert Camera.from_dict({"width": 64.0, "height": 32}).width == 64
