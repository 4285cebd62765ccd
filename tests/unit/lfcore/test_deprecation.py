"""The deprecation helper (lfcore._deprecation): old calls work, warn once, in one line."""

from __future__ import annotations

import warnings

import pytest

from lfcore._deprecation import deprecated, deprecated_alias, keyword_options, moved_names


def _options():
    @keyword_options("scale", "offset", since="0.1.0")
    def shift(x, *, scale=1.0, offset=0.0, label="x"):
        return x * scale + offset, label

    return shift


def test_positional_options_map_to_their_keywords_in_the_old_order():
    shift = _options()
    with pytest.warns(DeprecationWarning):
        assert shift(2.0, 3.0, 1.0) == (7.0, "x")
    assert shift(2.0, 3.0) == (6.0, "x")  # one of them
    assert shift(2.0, 3.0, label="y") == (6.0, "y")  # with the other keywords


def test_keyword_calls_do_not_warn():
    shift = _options()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert shift(2.0, scale=3.0, offset=1.0) == (7.0, "x")
        assert shift(2.0) == (2.0, "x")


def test_warns_once_per_function_in_one_line_naming_the_options():
    shift = _options()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        shift(2.0, 3.0)
        shift(2.0, 3.0, 1.0)
    assert len(caught) == 1
    (w,) = caught
    assert w.category is DeprecationWarning
    message = str(w.message)
    assert "\n" not in message
    assert "shift(): pass scale=, offset= by keyword" in message
    assert "since lfpiv 0.1.0" in message
    assert w.filename == __file__  # it points at the caller's line


def test_wrong_calls_raise_what_python_would():
    shift = _options()
    with pytest.raises(TypeError, match="takes 3 positional arguments but 4 were given"):
        shift(1.0, 2.0, 3.0, 4.0)
    with pytest.raises(TypeError, match="multiple values for argument 'scale'"):
        shift(1.0, 2.0, scale=3.0)


def test_methods_and_classmethods():
    class Grid:
        @keyword_options("device", since="0.1.0")
        def __init__(self, shape, *, device=None):
            self.shape, self.device = shape, device

        @classmethod
        @keyword_options("mode", since="0.1.0")
        def open(cls, path, *, mode="r"):
            return path, mode

    with pytest.warns(DeprecationWarning, match=r"Grid.__init__\(\): pass device="):
        assert Grid((2, 3), "cpu").device == "cpu"
    with pytest.warns(DeprecationWarning, match=r"Grid.open\(\): pass mode="):
        assert Grid.open("run.zarr", "r+") == ("run.zarr", "r+")
    assert Grid.open("run.zarr", mode="r+") == ("run.zarr", "r+")


def test_the_decorator_refuses_options_that_are_not_keyword_only():
    with pytest.raises(TypeError, match=r"\['scale'\] are not keyword-only"):
        keyword_options("scale", since="0.1.0")(lambda x, scale=1.0: x * scale)
    with pytest.raises(TypeError, match="takes \\*args"):
        keyword_options("scale", since="0.1.0")(lambda *x, scale=1.0: x)


def test_an_alias_calls_the_new_function_and_warns_once():
    def evaluate(store, pairs=None, *, option="--pair-range"):
        """The new one."""
        return store, pairs, option

    old = deprecated_alias(evaluate, "lfpiv.commands.correlate.evaluate_vectors", since="0.1.0")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert old("run", slice(1, 2)) == ("run", slice(1, 2), "--pair-range")
        assert old("run", option="--pairs") == ("run", None, "--pairs")
    assert len(caught) == 1
    message = str(caught[0].message)
    assert caught[0].category is DeprecationWarning
    assert "\n" not in message
    assert message.startswith("lfpiv.commands.correlate.evaluate_vectors is now ")
    assert message.endswith("evaluate (deprecated since lfpiv 0.1.0)")
    assert caught[0].filename == __file__


def test_moved_names_give_the_object_itself_and_warn_once():
    class New:
        """A class renamed."""

    getattr_ = moved_names("pkg.mod", {"Old": lambda: New}, since="0.1.0")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert getattr_("Old") is New and getattr_("Old") is New  # a class stays a class
    assert len(caught) == 1 and caught[0].category is DeprecationWarning
    message = str(caught[0].message)
    assert message.startswith("pkg.mod.Old is now ") and message.endswith("New (deprecated since lfpiv 0.1.0)")
    with pytest.raises(AttributeError, match="has no attribute 'Other'"):
        getattr_("Other")


def test_a_deprecated_method_still_works_and_says_what_to_use():
    class Thing:
        @deprecated("thing.new()", since="0.1.0")
        def old(self, x):
            return 2 * x

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert Thing().old(3) == 6 and Thing().old(4) == 8
    assert len(caught) == 1 and caught[0].filename == __file__
    assert str(caught[0].message).endswith("Thing.old() is deprecated since lfpiv 0.1.0: use thing.new()")


def test_the_reconstruction_cores_old_names_still_work():
    """Renamed with the operator protocol: each old name gives the new object, with a warning."""
    import lfcore.matrix_free as matrix_free
    import lfcore.pinhole_projector as pinhole_projector
    import lfcore.plan as plan
    import lfcore.projector as projector

    with pytest.warns(DeprecationWarning, match="lfcore.projector.Projector is now lfcore.projector.LightFieldProj"):
        assert projector.Projector is projector.LightFieldProjector
    with pytest.warns(DeprecationWarning, match="is now lfcore.matrix_free.TemplateOperator"):
        assert matrix_free.MatrixFreeWeights is matrix_free.TemplateOperator
    for name in ("projector_for", "default_method", "unsupported_method"):
        with pytest.warns(DeprecationWarning, match=f"lfcore.pinhole_projector.{name} is now lfcore.plan.{name}"):
            assert getattr(pinhole_projector, name) is getattr(plan, name)


def test_the_reconstruction_cores_positional_options_still_work():
    """Calls written before the options became keyword-only give the same results, warned."""
    import numpy as np

    from lfcore.projector import LightFieldProjector
    from lfcore.volume import VolumeGrid
    from lfcore.weight_cache import WeightCache
    from lfpiv.rigfile import load_rig
    from tests.conftest import EXAMPLES

    rig = load_rig(EXAMPLES / "tiny.toml")
    rig = rig.model_copy(update={"volume": rig.volume.model_copy(update={"size_mm": (0.3, 0.3, 0.6)})})
    proj = LightFieldProjector(rig.camera, VolumeGrid.from_rig(rig), device="cpu")
    vox = proj.all_voxels()[:50]
    with pytest.warns(DeprecationWarning, match="pass method=, min_weight=, budget_bytes=, build=, sort=, storage="):
        old = proj.weights(vox, "los")
    new = proj.weights(vox, method="los")
    for a, b in zip(old.to_numpy(), new.to_numpy(), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.warns(DeprecationWarning, match="pass budget_bytes=, min_weight=, checks=, method="):
        cache = WeightCache(proj, None, 1e-6, 0, "los")
    assert cache.method == "los" and cache.checks_bytes == 0
