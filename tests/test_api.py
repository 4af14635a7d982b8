"""The public API: what a notebook sees, introspected."""

import inspect

import volshade as vs


def _public_callables():
    for name in dir(vs):
        if name.startswith("_"):
            continue
        obj = getattr(vs, name)
        if inspect.isfunction(obj):
            yield name, obj


def test_options_are_keyword_only():
    # Public kernels take their data positionally and every option by keyword.
    data_args = {"render": 2, "composite": 2, "save_png": 2, "viewpoint_saliency": 3,
                 "most_salient_view": 3, "least_salient_view": 3, "projected_area": 2,
                 "modulate_opacity": 2, "threshold": 3, "obscurance_shading": 4,
                 "merge_feature_ao": 2, "clip_mask": 2, "affected_mask": 2, "clip_opacity": 2,
                 "fit": 3}
    for name, fn in _public_callables():
        params = list(inspect.signature(fn).parameters.values())
        positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        allowed = data_args.get(name, 1)
        assert len(positional) <= allowed, f"vs.{name} takes options positionally: {positional}"


def test_no_rng_argument_names():
    for name, fn in _public_callables():
        assert "rng" not in inspect.signature(fn).parameters, f"vs.{name}: call it `key`"


def test_public_functions_have_docstrings():
    for name, fn in _public_callables():
        assert fn.__doc__ and len(fn.__doc__.strip()) > 20, f"vs.{name} has no docstring"
    for cls in (vs.Scene, vs.Camera, vs.TransferFunction, vs.Phong):
        assert cls.__doc__
