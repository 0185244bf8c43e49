"""Every value the page sends, wrong or absurd, over the real protocol (issue 29).

A real server (``dvr-perception app``, 16-voxel phantom) and a wslink/trame client on aiohttp
(:class:`tests.app.test_security.Client`).  Each state variable the page may set
(:data:`dvr_perception.app.page_input.STATE`) and each page action with arguments
(:data:`~dvr_perception.app.page_input.TRIGGERS`) gets a value of the wrong type and an
absurd one, one at a time: the page must show one message, the variable keep the server's
value, and the next valid action succeed.  Then the cases the issue names, malformed wslink
messages, and the server's whole log (no traceback).  The tests run in file order.
"""

from __future__ import annotations

import asyncio
import json

import pytest

from dvr_perception.app.page_input import STATE, TRIGGERS
from tests.app.test_security import Client, _open

aiohttp = pytest.importorskip("aiohttp")

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]

HUGE = 1e308
NAN = float("nan")
#: A small volume as an upload: 16^3 voxels, uint8, a ramp along x.
NRRD = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 16 16 16\nencoding: raw\n\n" + bytes(
    (x * 16) % 256 for _ in range(256) for x in range(16)
)

#: Per state variable: a value of the wrong type, an absurd value, and a valid value.
STATE_CASES = {
    "volume_name": (12, "x" * 5000, "phantom"),
    "upload": ([1, 2], {"name": "a.nrrd", "size": -5, "content": b""}, None),
    "orientation_code": (5, "../../etc", ""),
    "spec_name": (["a.json"], "x" * 5000, "mine.json"),
    "show_map": ("yes", 2, True),
    "map_kind": (3, "../../etc", "shape"),
    "map_opacity": ("0.5", HUGE, 0.5),
    "tab": (1, "../../etc", "quality"),
    "lens_shape": (None, "hexagon", "circle"),
    "lens": (
        "rect",
        {"shape": "rect", "x0": HUGE, "y0": 0.1, "x1": 0.5, "y1": 0.5, "w": 100, "h": 100},
        {"shape": "rect", "x0": 0.1, "y0": 0.1, "x1": 0.6, "y1": 0.7, "w": 100, "h": 100},
    ),
    "cal_name": (5, "x" * 5000, "mine.json"),
    "use_calibration": ("true", 5, True),
    "cal_rating": ("0.5", NAN, 0.3),
    "rank_structure": ("0", 10**6, 1),
    "rank_order": ("img1 img2", [f"img{k}" for k in range(1000)], ["img1", "img2"]),
    "tf_edit": (
        "drag",
        {"index": 0, "kind": "lo", "fx": HUGE, "fy": 0.5},
        {"index": 0, "kind": "opacity", "fx": 0.5, "fy": 0.5},
    ),
    "show_legend": ("no", 7, False),
    "error": (5, "x" * 100_000, ""),
    "info": ([], "x" * 100_000, ""),
}

#: Per page action: wrong-type arguments and absurd ones.
TRIGGER_CASES = {
    "set_importance": (["0", 0.5], [0, HUGE]),
    "set_range": ([0, 0, [1]], [0, 0, "1e308"]),
    "set_colour": ([0, {"r": 1, "g": 0, "b": 0}], [0, "#gggggg"]),
    "load_spec": ([5], ["x" * 5000]),
    "save_spec": ([[1]], ["x" * 5000]),
    "undo": (["1"], [10**9]),
    "optimise": ([["opacity"]], ["../../etc"]),
    "set_lens_target": ([0, "vis", "x"], [0, "vis", HUGE]),
    "rate_stimulus": (["a"], [float("inf")]),
    "save_ranking": ([[1, 2, 3]], [["../../etc"]]),
    "local_camera": (
        ["camera"],
        [{"position": [HUGE, 0, 0], "focalPoint": [0, 0, 0], "viewUp": [0, 1, 0]}],
    ),
    "view_axis": ([1], ["../../etc"]),
    "view_patient": ([None], ["x" * 1000]),
}
NO_ARGUMENTS = sorted(n for n, a in TRIGGERS.items() if not a.rules and a.whole is None)


def test_the_cases_cover_every_rule():
    assert set(STATE_CASES) == set(STATE)
    assert set(TRIGGER_CASES) | set(NO_ARGUMENTS) == set(TRIGGERS)


@pytest.fixture(scope="module")
def server(tmp_path_factory, vtk_can_render, app_server):
    root = tmp_path_factory.mktemp("page_input")
    start, stop = app_server
    args = ["--state-dir", str(root / "state"), "--phantom-size", "16", "--iterations", "2"]
    srv = start(root, args)
    try:
        yield {**srv, "root": root}
    finally:
        stop(srv["proc"])


def _run(coro):
    return asyncio.run(coro)


async def _session(srv, work):
    async with aiohttp.ClientSession() as session:
        c = await _open(session, srv)
        try:
            return await work(c)
        finally:
            await c.ws.close()


async def _settled(c: Client, *, timeout: float = 240) -> dict:
    """Wait until no measurement or optimisation runs; return the state."""
    for _ in range(int(timeout / 0.2)):
        st = await c.state()
        if not st["measuring"] and not st["busy"]:
            return st
        await asyncio.sleep(0.2)
    raise AssertionError("the server kept measuring")


def _one_refusal(error: str, label: str) -> None:
    assert error.startswith("refused: "), error
    assert error.count("refused") == 1, error
    assert label in error, error
    assert "unexpected" not in error
    assert "Traceback" not in error


@pytest.mark.parametrize("name", sorted(STATE_CASES))
def test_a_wrong_or_absurd_state_value_is_one_message_and_changes_nothing(server, name):
    wrong, absurd, valid = STATE_CASES[name]
    label = STATE[name].label

    async def work(c: Client):
        out = []
        for bad in (wrong, absurd):
            await c.update(error="", info="")
            before = (await c.state()).get(name)
            await c.update(**{name: bad})
            st = await c.state()
            out.append((st["error"], before, st.get(name)))
        await c.update(error="")
        await c.update(**{name: valid})
        st = await _settled(c)
        return out, st

    out, st = _run(_session(server, work))
    for error, before, after in out:
        if name in ("error", "info"):
            assert after == (error if name == "error" else "")  # the refusal took its place
        else:
            assert after == before  # the server's value stays
        _one_refusal(error, label)
    # the next valid value is taken, without a message
    assert st["error"] == "", st["error"]
    if name not in ("tf_edit", "upload"):  # these two are consumed by their handler
        assert st[name] == valid


@pytest.mark.parametrize("kind", ["wrong type", "absurd"])
@pytest.mark.parametrize("name", sorted(TRIGGER_CASES))
def test_wrong_or_absurd_action_arguments_are_one_message(server, name, kind):
    args = TRIGGER_CASES[name][kind == "absurd"]

    async def work(c: Client):
        names = await _trigger_names(c)
        await c.update(error="", info="")
        before = await _settled(c)
        reply = await c.call("trame.trigger", [names[name], args, {}])
        st = await c.state()
        return reply, before, st

    reply, before, st = _run(_session(server, work))
    assert "error" not in reply, reply  # the call is answered, the client stays
    _one_refusal(st["error"], "")
    assert st["now_key"] == before["now_key"]  # neither the view nor the settings changed
    assert st["history"] == before["history"]


@pytest.mark.parametrize("name", NO_ARGUMENTS)
def test_an_action_without_arguments_refuses_some(server, name):
    async def work(c: Client):
        names = await _trigger_names(c)
        await c.update(error="")
        await c.call("trame.trigger", [names[name], ["extra"], {}])
        return (await c.state())["error"]

    error = _run(_session(server, work))
    _one_refusal(error, f"page action {name}: expected 0 arguments, got 1")


_NAMES: dict = {}


async def _trigger_names(c: Client) -> dict:
    """Map each page handler to its trigger name (each refusal names its handler)."""
    if _NAMES:
        return _NAMES
    template = (await c.state())["trame__template_main"]
    import re

    for trigger in sorted(set(re.findall(r"trigger\('(trigger__\d+)'", template))):
        await c.update(error="")
        await c.call("trame.trigger", [trigger, list(range(9)), {}])
        m = re.search(r"page action (\w+): expected", (await c.state())["error"])
        assert m, f"{trigger} was not refused"
        _NAMES[m.group(1)] = trigger
    assert set(TRIGGERS) == set(_NAMES), set(TRIGGERS) ^ set(_NAMES)
    return _NAMES


def test_server_owned_variables_cannot_be_set_by_the_page(server):
    async def work(c: Client):
        before = await c.state()
        await c.update(error="")
        await c.update(
            lens_rows="x", rank_images=5, measured_key=[], trame__template_main="<b>x</b>"
        )
        return before, await c.state()

    before, st = _run(_session(server, work))
    _one_refusal(st["error"], "lens_rows: set by the server")
    assert st["error"].endswith("(and 1 more)")  # three reasons shown, then the count
    for key in ("lens_rows", "rank_images", "measured_key", "trame__template_main"):
        assert st[key] == before[key]


def test_map_kind_escape_does_not_stick(server):
    """``map_kind='../../etc'`` made every later volume load fail until reset."""

    async def work(c: Client):
        await c.update(error="", map_kind="visibility")
        await c.update(show_map=True, map_kind="../../etc")
        refused = (await c.state())["error"]
        await c.update(error="")
        await c.update(upload={"name": "ramp.nrrd", "size": len(NRRD), "content": NRRD})
        st = await _settled(c)
        await c.update(show_map=False)
        return refused, st

    refused, st = _run(_session(server, work))
    _one_refusal(refused, "map kind '../../etc': expected one of visibility, shape")
    assert st["error"] == "", st["error"]
    assert st["volume_name"] == "uploaded/ramp.nrrd"
    assert st["map_kind"] == "visibility"
    assert st["measured_key"] == st["now_key"]  # measured, with the map of a valid kind
    assert st["map_shown"] == "visibility"


def test_a_far_camera_is_refused_and_measuring_goes_on(server):
    """A camera at 1e308 killed the background re-measure; now it is refused."""

    async def work(c: Client):
        names = await _trigger_names(c)
        far = {"position": [HUGE, HUGE, HUGE], "focalPoint": [0, 0, 0], "viewUp": [0, 1, 0]}
        await c.update(error="")
        await c.call("trame.trigger", [names["local_camera"], [far], {}])
        refused = (await c.state())["error"]
        await c.update(error="")
        await c.call("trame.trigger", [names["view_axis"], ["+Y"], {}])
        st = await _settled(c)
        return refused, st

    refused, st = _run(_session(server, work))
    _one_refusal(refused, "camera")
    assert "position within" in refused
    assert st["error"] == ""
    assert st["measured_key"] == st["now_key"]  # the new view was measured


@pytest.mark.parametrize(
    ("what", "name", "args", "says"),
    [
        ("string tf_edit", "tf_edit", "lo", "transfer-function edit 'lo'"),
        ("dict colour", "set_colour", [0, {"r": 1}], "colour <a dict of 1 keys>"),
        ("list for optimise", "optimise", [["all"]], "optimise stages <a list of 1 items>"),
        ("list as upload content", "upload", [1, 2, 3], "upload content as bytes"),
    ],
)
def test_the_wrong_types_the_issue_names(server, what, name, args, says):
    async def work(c: Client):
        await c.update(error="")
        if name == "tf_edit":
            await c.update(tf_edit=args)
        elif name == "upload":
            await c.update(upload={"name": "x.nrrd", "size": 3, "content": args})
        else:
            names = await _trigger_names(c)
            await c.call("trame.trigger", [names[name], args, {}])
        return (await c.state())["error"]

    _one_refusal(_run(_session(server, work)), says)


@pytest.mark.parametrize(
    ("message", "reply_expected"),
    [
        ({"wslink": "1.0", "id": "rpc:c0:901", "args": [], "kwargs": {}}, True),  # no method
        ({"wslink": "1.0", "id": "rpc:c0:902", "method": 5}, True),
        ({"wslink": "1.0", "id": 903, "method": "trame.state.get"}, False),
        ({"wslink": "1.0", "id": "rpc:c0:904", "method": "trame.state.get", "args": 5}, True),
        ({"wslink": "1.0", "id": "rpc:c0:905", "method": "trame.trigger", "args": [1]}, True),
        ({"wslink": "1.0", "id": "rpc:c0:906", "method": "trame.state.update", "args": [5]}, False),
        ({"id": "rpc:c0:907", "method": "trame.lifecycle.update", "args": ["server_ready"]}, False),
        ({"id": "rpc:c0:908", "method": "trame.trigger", "args": ["nope", [], {}]}, False),
        ([1, 2, 3], False),
        (7, False),
        ({"id": "rpc:c0:909", "method": "application.exit", "args": []}, True),  # stops the server
        ({"id": "rpc:c0:910", "method": "application.exit.later", "args": [0]}, True),
        ({"id": "rpc:c0:911", "method": "viewport.image.push", "args": ["bad"]}, False),
        ({"id": "rpc:c0:912", "method": "trame.force.push", "args": [[1]]}, False),
        (
            {"id": "rpc:c0:913", "method": "trame.error.client", "args": ["a\nline two\x1b[31m"]},
            False,
        ),
    ],
)
def test_a_malformed_message_is_refused_quietly_and_the_client_stays(
    server, message, reply_expected
):
    async def work(c: Client):
        await c.send(message)
        if reply_expected:
            hit = []
            for _ in range(20):  # the refusal answers the message's id
                await c.call("trame.state.get", [])
                hit = [m for m in c.received if m.get("id") == message["id"]]
                if hit:
                    break
                await asyncio.sleep(0.1)
            assert hit, "no answer to the refused message"
            answer = hit[0]
        else:
            answer = None
            await asyncio.sleep(0.3)
        reply = await c.call("trame.state.get", [])  # the same connection still works
        return answer, reply

    answer, reply = _run(_session(server, work))
    assert "result" in reply
    if reply_expected:
        assert answer["error"]["message"].startswith("message refused: "), answer
        assert "trace" not in json.dumps(answer)


def test_the_log_has_no_traceback_and_the_app_still_works(server):
    async def work(c: Client):
        names = await _trigger_names(c)
        await c.update(error="")
        await c.update(tf_edit={"index": 1, "kind": "opacity", "fx": 0.5, "fy": 0.4})
        await c.call("trame.trigger", [names["reset_view"], [], {}])
        return await _settled(c)

    st = _run(_session(server, work))
    assert st["error"] == "", st["error"]
    assert st["measured_key"] == st["now_key"]
    assert server["proc"].poll() is None
    log = server["log"].read_text()
    for bad in ("Traceback", "Exception raised", "unexpected ", "measuring failed", "\x1b"):
        assert bad not in log, log[-3000:]
    assert "SIGTERM" not in log  # application.exit did not stop it
    assert "websocket call viewport.image.push refused: TypeError" in log
    refusals = [line for line in log.splitlines() if "refused" in line]
    assert len(refusals) >= 2 * len(STATE) + 2 * len(TRIGGER_CASES)
    assert all(line.startswith("dvr-perception: ") for line in refusals)
    assert any("message refused: a message without a method" in line for line in refusals)
