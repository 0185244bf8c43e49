"""One spelling in the public API, "colour"; the "color" names warn for one release and work."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.structures.io import load_spec, save_spec, spec_from_dict, spec_to_dict
from dvr_perception.structures.spec import Structure

OLD = pytest.warns(DeprecationWarning, match="deprecated")


def _spec_dict(**colour_keys) -> dict:
    s = {"name": "bone", "range": [10, 20], "importance": 0.5, **colour_keys}
    return {"version": 1, "structures": [{"name": "air", "range": [0, 10], "importance": 0.2,
                                          "colour": [0, 0, 1]}, s]}  # fmt: skip


# -- Structure ------------------------------------------------------------------------------------
def test_structure_colour_and_its_deprecated_color_alias():
    new = Structure("bone", 0.5, (1.0, 0.5, 0.0), range=(0.0, 1.0))
    assert new.colour == (1.0, 0.5, 0.0)
    assert [f.name for f in dataclasses.fields(Structure)][:3] == ["name", "importance", "colour"]
    with pytest.warns(DeprecationWarning, match=r"Structure\(color=\.\.\.\) is deprecated"):
        old = Structure(name="bone", importance=0.5, color=(1.0, 0.5, 0.0), range=(0.0, 1.0))
    assert old == new
    with pytest.warns(DeprecationWarning, match="Structure.color is deprecated"):
        assert old.color == (1.0, 0.5, 0.0)
    with pytest.raises(TypeError, match="both color= and colour="):
        Structure(name="b", importance=0.5, color=(1, 1, 1), colour=(1, 1, 1), range=(0, 1))
    assert dataclasses.replace(new, colour=(0.0, 0.0, 0.0)).colour == (0.0, 0.0, 0.0)


# -- spec files: both keys are read, "colour" is written ---------------------------------------
def test_spec_files_read_colour_and_color_and_write_colour(tmp_path):
    a = spec_from_dict(_spec_dict(colour=[1, 0.5, 0]))
    b = spec_from_dict(_spec_dict(color=[1, 0.5, 0]))
    assert a == b
    assert a.structures[1].colour == (1.0, 0.5, 0.0)
    written = spec_to_dict(b)["structures"][1]
    assert written["colour"] == [1.0, 0.5, 0.0]
    assert "color" not in written
    save_spec(b, tmp_path / "s.json")
    assert '"color"' not in (tmp_path / "s.json").read_text()
    assert load_spec(tmp_path / "s.json") == a


def test_a_structure_giving_both_colour_keys_is_an_error_naming_file_and_structure(tmp_path):
    path = tmp_path / "both.json"
    path.write_text(json.dumps(_spec_dict(colour=[1, 0, 0], color=[1, 0, 0])))
    with pytest.raises(DVRInputError, match=r"both\.json: structures\[1\] \('bone'\) gives both"):
        load_spec(path)


def test_a_missing_colour_names_the_new_key():
    with pytest.raises(DVRInputError, match=r"structures\[1\]\.colour is missing"):
        spec_from_dict(_spec_dict())
    with pytest.raises(DVRInputError, match=r"structures\[1\]\.color\[1\] must be in \[0, 1\]"):
        spec_from_dict(_spec_dict(color=[1, 2, 0]))


# -- reevaluate(colors=) and the optimiser's parameters -------------------------------------------
def test_reevaluate_colors_keyword_warns_and_gives_the_same_picture():
    from dvr_perception import make_phantom
    from dvr_perception.rays import Camera, analyze, reevaluate

    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=12, height=10)
    cache = analyze(vol, spec, cam, build_cache=True).cache
    cols = np.tile([0.2, 0.7, 0.4], (len(spec.structures), 1))
    new = reevaluate(cache, colours=cols)
    with pytest.warns(DeprecationWarning, match=r"reevaluate\(colors=\.\.\.\) is deprecated"):
        old = reevaluate(cache, colors=cols)
    np.testing.assert_array_equal(old.rgba, new.rgba)
    assert not np.array_equal(new.rgba, reevaluate(cache).rgba)  # the colours did change it
    with pytest.raises(TypeError, match="both colors= and colours="):
        reevaluate(cache, colors=cols, colours=cols)


def test_rank_cache_reevaluate_takes_the_old_keyword_too():
    from dvr_perception.distributed import RankCache

    class Reached(Exception):
        pass

    class Probe:  # stops the method at its first use of the cache: the keyword was accepted
        def __getattr__(self, name):
            raise Reached(name)

    with OLD, pytest.raises(Reached):
        RankCache.reevaluate(Probe(), colors=[[1.0, 0.0, 0.0]])
    with pytest.raises(TypeError, match="both colors= and colours="):
        RankCache.reevaluate(Probe(), colors=[[1.0, 0, 0]], colours=[[1.0, 0, 0]])


def test_optimiser_params_colours_and_their_deprecated_alias():
    from dvr_perception import make_phantom
    from dvr_perception.optimize._problem import Params

    _, spec = make_phantom(size=16)
    p = Params.from_spec(spec)
    assert p.colours.shape == (len(spec.structures), 3)
    with OLD:
        np.testing.assert_array_equal(p.colors, p.colours)
    zeros = np.zeros_like(p.colours)
    with pytest.warns(DeprecationWarning, match=r"Params.replace\(colors=\.\.\.\)"):
        q = p.replace(colors=zeros)
    assert q.same(p.replace(colours=zeros))
    with pytest.warns(DeprecationWarning, match=r"Params\(colors=\.\.\.\)"):
        r = Params(opacities=p.opacities, lighting=p.lighting, colors=zeros, light=p.light)
    assert r.same(q)
    assert [x.colour for x in q.to_spec(spec).structures] == [(0.0, 0.0, 0.0)] * len(zeros)


def test_explain_reads_the_old_colour_keys_with_a_warning():
    from dvr_perception.optimize.explain import explain

    names, shares = ["a", "b"], {"a": 0.5, "b": 0.5}
    before = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    after = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    args = (names, [0.5, 0.5], [0.5, 0.5], shares, shares, shares)
    new = explain(*args, colour={"colours_before": before, "colours_after": after})
    with OLD:
        old = explain(*args, colour={"colors_before": before, "colors_after": after})
    assert old == new
    assert new["a"]["colour"] is not None  # red to green is a change the text reports
    assert new["b"]["colour"] is None


def test_spec_from_vtk_old_keyword():
    from dvr_perception import make_phantom
    from dvr_perception.export import spec_from_vtk, to_vtk_transfer_functions

    _, spec = make_phantom(size=16)
    ctf, otf = to_vtk_transfer_functions(spec)
    new = spec_from_vtk(colour_tf=ctf, opacity_tf=otf, names=list(spec.names))
    with OLD:
        old = spec_from_vtk(color_tf=ctf, opacity_tf=otf, names=list(spec.names))
    assert old == new
    got = [s.colour for s in new.structures]
    np.testing.assert_allclose(got, [s.colour for s in spec.structures], atol=1e-3)
