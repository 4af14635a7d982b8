"""NaN and inf are refused by the display and importance helpers, eagerly and under jit."""

import jax
import jax.numpy as jnp
import pytest

from volshade import _checks
from volshade.clip import SphereClip, affected_mask
from volshade.importance import Importance, focus_weights, sample_importance
from volshade.obscurance import obscurance_shading, threshold
from volshade.saliency import modulate_opacity, opacity_factor
from volshade.transfer import preset

TF = preset("grey")
NAN = jnp.asarray([0.2, jnp.nan, 0.4])
INF = jnp.asarray([0.2, jnp.inf, 0.4])

CASES = {
    "threshold": (lambda x: threshold(x, 0.2, 0.8), "obscurance"),
    "threshold bounds": (lambda x: threshold(jnp.ones(3), x[1], 0.8), "finite"),
    "obscurance_shading normal": (
        lambda x: obscurance_shading(jnp.stack([x, x, x], -1), (0, 0, 1), (1, 0, 0), jnp.ones(3)),
        "normal"),
    "obscurance_shading obscurance": (
        lambda x: obscurance_shading(jnp.ones((3, 3)), (0, 0, 1), (1, 0, 0), x), "obscurance"),
    "sample_importance": (lambda x: sample_importance(Importance(intensity=1.0), intensity=x),
                          "intensity"),
    "focus_weights center": (lambda x: focus_weights((4, 4), center=x[:2][::-1], radius=1.0),
                             "center"),
    "focus_weights radius": (lambda x: focus_weights((4, 4), center=(1.0, 1.0), radius=x[1]),
                             "radius"),
    "opacity_factor threshold": (lambda x: opacity_factor(jnp.ones((2, 2, 2)), threshold=x[1]),
                                 "threshold"),
    "TransferFunction.opacity": (lambda x: TF.opacity(x), r"TransferFunction\.opacity.*volume"),
    "TransferFunction.color": (lambda x: TF.color(x), r"TransferFunction\.color.*volume"),
    "TransferFunction.extinction": (lambda x: TF.extinction(x),
                                    r"TransferFunction\.extinction.*volume"),
    "TransferFunction call": (lambda x: TF(x, step=0.5), r"TransferFunction\.__call__.*volume"),
    "sample_importance global_weight": (
        lambda x: sample_importance(Importance(intensity=1.0), intensity=jnp.ones(3),
                                    global_weight=x), "global_weight"),
    "focus_weights inside": (
        lambda x: focus_weights((4, 4), center=(1.0, 1.0), radius=1.0, inside=x[1]), "inside"),
    "affected_mask radius": (
        lambda x: affected_mask((4, 4, 4), SphereClip(center=(1.0, 1.0, 1.0), radius=1.0),
                                radius=x[1]), "radius"),
    "modulate_opacity threshold": (
        lambda x: modulate_opacity(jnp.ones((2, 2, 2)), jnp.ones((2, 2, 2)), threshold=x[1]),
        "threshold"),
}


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("bad", [NAN, INF], ids=["nan", "inf"])
@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_non_finite_input_is_refused(name, bad, jit):
    fn, argument = CASES[name]
    fn = jax.jit(fn) if jit else fn
    with pytest.raises(Exception, match=argument):
        jax.block_until_ready(fn(bad))
    fn(jnp.asarray([0.2, 0.3, 0.4]))  # the same call with finite values runs


def test_integer_importance_weights_are_accepted():
    imp, _ = sample_importance(Importance(intensity=2), intensity=jnp.ones(3))
    assert imp.tolist() == [2.0, 2.0, 2.0]


def test_modulate_opacity_refuses_saliency_outside_the_unit_range():
    # a saliency below 0 would give negative opacities, above 1 opacities clipped to 1
    for value in (-0.5, 1.5):
        with pytest.raises(Exception, match=r"`saliency` .*\[0, 1\]"):
            modulate_opacity(jnp.full((1, 1, 2), 0.5), jnp.full((1, 1, 2), value), threshold=-1.0)


def test_sample_importance_refuses_features_it_would_clip():
    imp = Importance(extinction=1.0, lighting=1.0)
    for features, name in ((dict(extinction=jnp.asarray([-5.0, 1.0])), "extinction"),
                           (dict(optical_depth=jnp.asarray([-1.0])), "optical_depth"),
                           (dict(gradient_magnitude=jnp.asarray([2.0])), "gradient_magnitude")):
        for fn in (sample_importance, jax.jit(sample_importance)):
            with pytest.raises(Exception, match=f"`{name}` must"):
                jax.block_until_ready(fn(imp, **features))


def test_traced_checks_of_one_call_report_the_first_that_fails():
    # one error site for all the traced checks of a call: its message is that of the
    # first check that holds, under jit and under vmap (from any element of the batch)
    def checked(x):
        return _checks.refuse(x, [(x[0] < 0, "first"), (x[1] < 0, "second"),
                                  (x[2] < 0, "third")], "f")

    for x, message in (([1, -1, -1], "second"), ([-1, 1, -1], "first"), ([1, 1, -1], "third")):
        with pytest.raises(Exception, match=f"f: {message}"):
            jax.block_until_ready(jax.jit(checked)(jnp.asarray(x, float)))
        with pytest.raises(ValueError, match=f"f: {message}"):  # eager: at once
            checked(jnp.asarray(x, float))
    batch = jnp.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, -1.0]])
    with pytest.raises(Exception, match="f: third"):
        jax.block_until_ready(jax.jit(jax.vmap(checked))(batch))
    assert jax.jit(jax.vmap(checked))(jnp.abs(batch)).tolist() == jnp.abs(batch).tolist()


@pytest.mark.parametrize("size", [3, 20], ids=["host", "compiled"])
def test_volume_checks_give_the_same_verdict_eagerly_traced_and_closed_over(size):
    # an eager check of a small array runs in NumPy, of a large one (20^3 > 4096 values)
    # as one compiled program, also when a jitted function closes over it; traced, it
    # is a run-time error: the same message each way, NaN before the range
    def check(x):
        return _checks.finite(x, "alpha", "f", unit_range=True)

    good = jnp.full((size,) * 3, 0.5)
    cases = ((good.at[1, 1, 1].set(jnp.nan).at[0, 0, 0].set(2.0), "contains NaN or inf"),
             (good.at[1, 1, 1].set(-jnp.inf), "contains NaN or inf"),
             (good.at[1, 1, 1].set(1.5), r"must lie in \[0, 1\]"),
             (good.at[1, 1, 1].set(-1e-30), r"must lie in \[0, 1\]"))
    for bad, message in cases:
        with pytest.raises(ValueError, match=f"f: `alpha` {message}"):
            check(bad)
        with pytest.raises(Exception, match=f"f: `alpha` {message}"):
            jax.block_until_ready(jax.jit(check)(bad))
        with pytest.raises(Exception, match=f"f: `alpha` {message}"):
            jax.block_until_ready(jax.jit(lambda bad=bad: check(bad))())
    # and a clean volume passes each way, unchanged
    for out in (check(good), jax.jit(check)(good), jax.jit(lambda: check(good))(),
                jax.jit(jax.vmap(check))(good[None])[0]):
        assert jnp.array_equal(out, good)
    # closed over, the check ran in the trace: staged there, the volume was a constant
    # whose reductions XLA folded while compiling (found by a review: a jitted lao of the
    # head at full resolution compiled for 25 s, contextual_ao for 52 s)
    assert not jax.make_jaxpr(lambda: check(good))().eqns
