"""Input validation shared by the public entry points.

Shape, dtype and static-option errors are raised at trace time as ``TypeError``
or ``ValueError`` naming the function, the argument and the fix. Value checks go
through :func:`refuse`: a ``ValueError`` at once on concrete data (an eager call),
``eqx.error_if`` on traced data, so they survive ``jax.jit``; callers must use the
returned array, or the check is dead code.
"""

import functools
from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array


def _big_ints(x: Any, name: str, where: str) -> Array:
    """``x``, holding Python ints past JAX's integer dtype (``jnp.asarray`` overflows:
    ``2**31`` without x64), as the default float, which holds them (a scalar weakly
    typed, as a Python float); ints past a float's range (``10**400``) refused by name
    (both were a bare ``OverflowError``)."""
    try:
        values = np.asarray(x, dtype=float)
    except OverflowError as err:
        raise ValueError(f"{where}: `{name}` holds an integer beyond the range of a float, "
                         f"got {x!r:.80}.") from err
    return jnp.asarray(values.tolist())


def as_float_array(x: Any, name: str, where: str) -> Array:
    """``x`` as a JAX array of a floating dtype (integers are promoted, other dtypes refused)."""
    try:
        arr = jnp.asarray(x)
    except OverflowError:
        arr = _big_ints(x, name, where)
    except (TypeError, ValueError) as err:  # ValueError: None, a ragged nested list
        # a transfer function or its method where its values belong (DESIGN.md's
        # `colors=tf.color`): say what to call
        classifier = any(hasattr(v, "opacity") for v in (x, getattr(x, "__self__", None)))
        hint = ("; classify the volume first, e.g. `tf.opacity(volume)` or "
                "`tf.color(volume)`" if classifier else "")
        raise TypeError(f"{where}: `{name}` must be an array of numbers (or a rectangular "
                        f"nested list of them), got {type(x).__name__}{hint}.") from err
    if jnp.issubdtype(arr.dtype, jnp.floating):
        return arr
    if jnp.issubdtype(arr.dtype, jnp.integer) or arr.dtype == jnp.bool_:
        return _default_float(arr)
    raise TypeError(
        f"{where}: `{name}` must have a real floating or integer dtype, got {arr.dtype}; "
        f"convert it with `.astype(jnp.float32)`."
    )


def holds_bool(x: Any) -> bool:
    """Whether ``x`` is a bool, a bool array, or a (nested) sequence holding a bool (which
    NumPy would promote with the numbers beside it)."""
    if isinstance(x, bool | np.bool_):
        return True
    if isinstance(x, list | tuple):
        return any(holds_bool(v) for v in x)
    return getattr(x, "dtype", None) == np.bool_


def numbers(x: Any, name: str, where: str) -> Array:
    """:func:`as_float_array` for a parameter: a bool, or a sequence holding one, is
    refused, not taken as 0 or 1 (data such as a mask keeps :func:`as_float_array`)."""
    if holds_bool(x):
        raise TypeError(f"{where}: `{name}` must be a number or numbers, got a bool in "
                        f"{x!r:.80}.")
    return as_float_array(x, name, where)


def floating_dtype(dtype: Any, where: str) -> Any:
    """``dtype`` if it is a floating dtype; an integer one would truncate every value."""
    try:
        given = jnp.dtype(dtype)
    except TypeError as err:
        raise TypeError(f"{where}: `dtype` must be a floating dtype (e.g. jnp.float32), got "
                        f"{dtype!r:.80}.") from err
    if not jnp.issubdtype(given, jnp.floating):
        raise TypeError(f"{where}: `dtype` must be a floating dtype, got {given}.")
    return dtype


def float_leaf(x: Any, name: str = "value", where: str = "volshade") -> Array:
    """A parameter leaf as an array of a floating dtype. An int (``d_max=16``,
    ``fov=30``) would otherwise stay an integer leaf, which ``jax.grad`` refuses and
    ``eqx.filter_grad`` silently skips; real floating dtypes are kept as given.
    Anything else (a string, ``None``, a bool, a complex number) is refused, naming
    ``name``: a bool would pass as 0 or 1 and a complex number would render its real
    part (also beside numbers, ``(True, 4.0, 4.0)``, which NumPy would promote)."""
    try:
        arr = jnp.asarray(x)
    except OverflowError:
        arr = _big_ints(x, name, where)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{where}: `{name}` must be a real number or an array of them, "
                        f"got {x!r}.") from err
    if holds_bool(x) or not (jnp.issubdtype(arr.dtype, jnp.floating)
                             or jnp.issubdtype(arr.dtype, jnp.integer)):
        raise TypeError(f"{where}: `{name}` must be a real number or an array of them, "
                        f"got {x!r:.80} of dtype {arr.dtype}.")
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = _default_float(arr)
    return arr


def float_leaves(module: Any, names: tuple[str, ...], where: str) -> Any:
    """``module`` with its fields ``names`` made float arrays (:func:`float_leaf`): set
    with ``eqx.tree_at``, a field skipped its converter and may be a Python number, a
    tuple or a list."""
    return eqx.tree_at(lambda m: tuple(getattr(m, name) for name in names), module,
                       tuple(float_leaf(getattr(module, name), name, where) for name in names))


def scalar_fields(module: Any, names: Any, where: str, *, use: str = "", fix: str) -> None:
    """Refuse a field of ``module`` among ``names`` that is not a real scalar, naming it,
    ``use`` (what it must be a scalar for) and ``fix``; a field set with ``eqx.tree_at``
    skipped its converter, and is refused as that would."""
    for name in names:
        value = getattr(module, name)
        float_leaf(value, name, where)
        if jnp.ndim(value) != 0:
            raise ValueError(f"{where}: `{name}` must be a scalar{use}, got shape "
                             f"{jnp.shape(value)}; {fix}.")


def _default_float(arr: Array) -> Array:
    """An integer (or bool) array in the default float dtype. A Python int (a weakly typed
    array) stays weakly typed, as a Python float does: ``radius=2`` then computes and
    compiles as ``radius=2.0`` (a strong float64 under x64 promoted a float32 volume's
    result to float64; a strong float32 compiled again beside a later ``2.0``)."""
    if getattr(arr, "weak_type", False):
        return arr + 0.0
    return arr.astype(jnp.result_type(float))


def strongly_typed(tree: Any, dtype: Any) -> Any:
    """``tree`` with each weakly typed floating leaf (a Python number that a
    converter made an array) made a strongly typed array of the dtype it promotes to
    with ``dtype``, the computation's: an eager call of a compiled function would
    otherwise compile again when the same parameter comes as an array
    (``Phong(diffuse=0.5)``, then a fitted ``jnp.float32``), and the two now compute
    the same. (Under x64 a number thus takes a float32 volume's dtype before it meets
    the volume's values, not after: what a float32 array in its place computes.)"""
    def strong(x):
        if (isinstance(x, jax.Array) and getattr(x, "weak_type", False)
                and jnp.issubdtype(x.dtype, jnp.floating)):
            return x.astype(jnp.result_type(x, dtype))
        return x

    return jax.tree_util.tree_map(strong, tree)


def leaf(where: str, name: str) -> Callable[[Any], Array]:
    """The converter of the parameter field ``name`` of ``where`` (``eqx.field``):
    :func:`float_leaf`, with errors that name the field."""
    return functools.partial(float_leaf, name=name, where=where)


def at_least_float32(arr: Array) -> Array:
    """Half-precision floats as float32 (their values convert exactly): interpolation,
    classification and compositing are done in float32 at least."""
    if jnp.issubdtype(arr.dtype, jnp.floating) and jnp.finfo(arr.dtype).bits < 32:
        return arr.astype(jnp.float32)
    return arr


def as_working_float(x: Any, name: str, where: str) -> Array:
    """``x`` as an array of float32 or wider: integers and bools converted (interpolation
    and comparison in an integer dtype would truncate), half precision widened."""
    return at_least_float32(as_float_array(x, name, where))


# Concrete arrays up to this many elements are checked on the host, with NumPy: an eager
# check in jnp compiles an XLA program per operation, shape and dtype (about 25 ms each
# on a CPU, most of a first eager call's checks); larger ones (volumes) stay on their
# device, which a copy to the host would cost more than one compile.
_HOST_CHECK_SIZE = 4096


def array_module(*arrays: Any):
    """``numpy`` when every one of ``arrays`` is concrete and small, else ``jax.numpy``:
    the module to compute a check with (:func:`refuse` takes either's result)."""
    leaves = jax.tree_util.tree_leaves(arrays)
    if any(isinstance(x, jax.core.Tracer) or np.size(x) > _HOST_CHECK_SIZE for x in leaves):
        return jnp
    return np


def reading(result: Array, *checked: Any) -> Array:
    """``result``, made to read every array leaf of ``checked``. Under jit a result that
    ignores a checked input lets XLA prune that input's run-time check (a NaN input
    would pass unseen). Each input is multiplied by 0 before it is summed (a sum of
    large finite inputs could overflow), so the value and gradient are unchanged."""
    arrays = jax.tree_util.tree_leaves(eqx.filter(checked, eqx.is_array))
    read = sum(jnp.sum(0 * x) for x in arrays)
    return result + jnp.asarray(read).astype(result.dtype)


def for_check(*arrays: Any) -> tuple:
    """``(xp, *arrays)``: the module to compute a check with (:func:`array_module`) and
    ``arrays`` as its arrays."""
    xp = array_module(*arrays)
    return (xp, *(xp.asarray(x) for x in arrays))


def not_positive(x: Any) -> Array:
    """Whether ``x`` holds a value that is NaN, inf or <= 0 (a ``bad`` for :func:`refuse`)."""
    xp, x = for_check(x)
    return ~xp.all(xp.isfinite(x) & (x > 0))


def non_finite(x: Any, *, minus_inf: bool = False) -> Array:
    """Where ``x`` is NaN or inf; with ``minus_inf``, -inf is a value, not an error (an
    importance of -inf means "no background")."""
    xp, x = for_check(x)
    return ~(xp.isfinite(x) | ((x == -np.inf) if minus_inf else False))


def python_scalar(value: Any) -> Any:
    """A NumPy scalar (``np.int64(1)``, ``np.bool_(True)``, ``np.str_("max")``) as the
    Python value it holds, anything else as given (checked by its field): a converter for
    static fields, where equinox warns of a NumPy scalar as of an array."""
    return value.item() if isinstance(value, np.generic) else value


def flag(value: Any, name: str, where: str) -> bool:
    """A static on/off option: ``True`` or ``False`` only (a string such as ``"no"`` is
    truthy and would silently switch the option on)."""
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"{where}: `{name}` must be True or False, got {value!r}.")
    return bool(value)


def scalar(x: Any, name: str, where: str, *, unit: str = "", dtype: Any = None) -> Array:
    """A real scalar argument as an array of a floating dtype (``dtype`` if given), with
    trace-time type and shape checks naming ``unit`` (e.g. ``"voxels"``). A bool is
    refused, not taken as 0 or 1; so is a known value beyond the range of ``dtype``,
    which the cast would make inf (and a later check call "not finite")."""
    unit = f" ({unit})" if unit else ""
    if holds_bool(x):
        raise TypeError(f"{where}: `{name}` must be a number{unit}, got the bool {x!r}.")
    try:
        arr = as_float_array(x, name, where)  # refuses None, strings, complex numbers
    except TypeError as err:
        raise TypeError(f"{where}: `{name}` must be a real number{unit}, got "
                        f"{x!r:.80}.") from err
    if arr.ndim != 0:
        raise ValueError(f"{where}: `{name}` must be a scalar{unit}, got shape "
                         f"{tuple(arr.shape)}; for several values use `jax.vmap`.")
    if dtype is None:
        return arr
    # as given (NumPy keeps a Python float in float64; jnp.asarray may already have
    # rounded it to float32)
    given = concrete(x)
    largest = float(np.finfo(dtype).max)
    if given is not None and np.isfinite(given) and abs(float(given)) > largest:
        raise ValueError(f"{where}: `{name}` = {float(given):g}{unit} lies beyond the range "
                         f"of {np.dtype(dtype).name}, the dtype it is computed in "
                         f"(+-{largest:.4g}).")
    return arr.astype(dtype)


def traced(x: Any) -> bool:
    """Whether ``x`` is, or holds (a sequence, a pytree), a tracer."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x))


def concrete(x: Any) -> np.ndarray | None:
    """``x`` as a NumPy array when its value is known at trace time, else None (a tracer,
    or a sequence holding one)."""
    if traced(x):
        return None
    return np.asarray(x)


def refuse(x: Any, checks: list[tuple[Any, str]], where: str, *, traced: bool = True) -> Any:
    """``x``, refused for each ``(bad, message)`` whose ``bad`` holds anywhere: with
    ``ValueError`` at once when ``bad`` is known at trace time, with ``eqx.error_if`` at
    run time when it is traced. ``traced=False`` (for ``__check_init__``, which cannot
    return ``x``) leaves traced checks to a later call at the point of use.

    The traced checks become one ``eqx.branched_error_if`` (the message of the first
    that holds): each error site walks and formats the Python stack while tracing
    (tens of milliseconds under a solver), and a site per check cost about 3 s of the
    7.7 s of tracing a fit."""
    pending = []
    for bad, message in checks:
        known = concrete(bad)
        if known is None:
            pending.append((bad, f"{where}: {message}"))
        elif np.any(known):
            raise ValueError(f"{where}: {message}")
    if not traced or not pending:
        return x
    if len(pending) == 1:
        return eqx.error_if(x, pending[0][0], pending[0][1])
    holds = jnp.stack([jnp.any(bad) for bad, _ in pending])
    return eqx.branched_error_if(x, jnp.any(holds), jnp.argmax(holds),
                                 [message for _, message in pending])


def check_ndim(x: Array, ndim: int, name: str, where: str, layout: str) -> None:
    if x.ndim != ndim:
        raise ValueError(
            f"{where}: `{name}` must have {ndim} dimensions {layout}, got shape {tuple(x.shape)}; "
            f"for a batch, use `jax.vmap`."
        )
    if any(s == 0 for s in x.shape):
        raise ValueError(f"{where}: `{name}` must not be empty, got shape {tuple(x.shape)}.")


def volume(x: Any, name: str, where: str, *, unit_range: bool = False,
           non_negative: bool = False, hint: str | None = None) -> Array:
    """Validate a ``(D, H, W)`` volume: rank and dtype at trace time, finiteness (and
    optionally ``[0, 1]`` or ``>= 0``, ``hint`` saying how to get there) with
    :func:`refuse`."""
    arr = as_float_array(x, name, where)
    check_ndim(arr, 3, name, where, "(D, H, W)")
    return finite(arr, name, where, unit_range=unit_range, non_negative=non_negative,
                  hint=hint or _OPACITY_HINT)


_OPACITY_HINT = ("(opacities); map it through a transfer function or `jnp.clip` it "
                 "yourself")


def finite(arr: Array, name: str, where: str, *, unit_range: bool = False,
           non_negative: bool = False, hint: str = _OPACITY_HINT) -> Array:
    """``arr``, refused (:func:`refuse`) when it holds NaN or inf, or values outside
    [0, 1] (``unit_range``, :func:`in_unit_range`) or below 0 (``non_negative``);
    ``hint`` follows "must lie in [0, 1]" or "must be >= 0"."""
    return refuse(arr, finite_problems(arr, name, unit_range=unit_range,
                                       non_negative=non_negative, hint=hint), where)


def finite_problems(arr: Array, name: str, *, unit_range: bool = False,
                    non_negative: bool = False, hint: str = _OPACITY_HINT) -> list:
    """The checks of :func:`finite`, as ``(bad, message)`` pairs for :func:`refuse`, to be
    tied to a smaller array than ``arr`` (:func:`refuse` passes what it guards through a
    conditional, whose result XLA stores anew: a copy)."""
    flags = _value_flags(arr, finite=True, unit_range=unit_range, non_negative=non_negative)
    checks = [(flags.pop(0), f"`{name}` contains NaN or inf; clean the data (e.g. "
                             f"`jnp.nan_to_num`) first.")]
    if unit_range:
        checks.append((flags.pop(0), f"`{name}` must lie in [0, 1] {hint}."))
    if non_negative:
        checks.append((flags.pop(0), f"`{name}` must be >= 0 {hint}."))
    return checks


def holds_non_finite(arr: Array) -> Array:
    """Whether ``arr`` holds NaN or inf, as a ``bad`` for :func:`refuse` with a message
    of the caller's (the reduction of :func:`finite`: one compiled program for a large
    concrete array)."""
    (bad,) = _value_flags(arr, finite=True, unit_range=False)
    return bad


def in_unit_range(arr: Array, name: str, where: str, *, hint: str = _OPACITY_HINT,
                  traced: bool = True) -> Array:
    """``arr``, refused (:func:`refuse`, ``traced`` as there) when it holds values outside
    [0, 1] (NaN passes: :func:`finite` refuses it); ``hint`` follows "must lie in [0, 1]"."""
    (outside,) = _value_flags(arr, finite=False, unit_range=True)
    return refuse(arr, [(outside, f"`{name}` must lie in [0, 1] {hint}.")], where,
                  traced=traced)


def _value_flags(arr: Any, *, finite: bool, unit_range: bool,
                 non_negative: bool = False) -> list:
    """Whether ``arr`` holds NaN or inf (``finite``), values outside [0, 1]
    (``unit_range``; NaN is not outside) and values below 0 (``non_negative``), in that
    order, as ``bad``s for :func:`refuse`. A large
    concrete array (a volume passed to an eager call) is checked by one compiled
    program: op by op, each comparison and reduction compiled a program of its own for
    every new shape and dtype (seven for the two checks of an opacity volume)."""
    if not isinstance(arr, jax.core.Tracer) and np.size(arr) > _HOST_CHECK_SIZE:
        # run now even inside a trace (a volume closed over by a jitted function): staged
        # there, the volume became a constant of the caller's program and XLA folded the
        # reductions over it while compiling (12 s each for the 7.1 M voxels of the head,
        # 25 s for a jitted lao, 52 s for contextual_ao)
        with jax.ensure_compile_time_eval():
            flags = _compiled_value_flags(jnp.asarray(arr), finite, unit_range, non_negative)
        return list(np.asarray(flags))
    xp, host = for_check(arr)
    return _flags_of(xp, host, finite, unit_range, non_negative)


def _flags_of(xp, x, finite: bool, unit_range: bool, non_negative: bool) -> list:
    """The flags of :func:`_value_flags`, with float reductions where that is safe: XLA on
    a CPU stores the elementwise predicates of ``all(isfinite(x))`` and ``any(x < 0)``
    before reducing them (12.2 ms for 12.6 M floats, against 7.3 for ``sum(x * 0)``, NaN
    where a value is not finite, and the smallest value). The smallest and largest values
    are not used for NaN, which its fast min/max may drop; so they serve the range
    checks only beside the finiteness check, which reports NaN first. Host (NumPy) arrays
    are small and checked exactly as written."""
    if np.size(x) == 0:
        return [xp.asarray(False)] * (finite + unit_range + non_negative)
    if xp is np or not finite:  # (in NumPy, inf * 0 warns)
        return ([~xp.all(xp.isfinite(x))] if finite else []) + \
            ([xp.any((x < 0) | (x > 1))] if unit_range else []) + \
            ([xp.any(x < 0)] if non_negative else [])
    lo = xp.min(x)
    return [~xp.isfinite(xp.sum(x * 0))] + \
        ([(lo < 0) | (xp.max(x) > 1)] if unit_range else []) + \
        ([lo < 0] if non_negative else [])


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _compiled_value_flags(x: Array, finite: bool, unit_range: bool,
                          non_negative: bool) -> Array:
    return jnp.stack(_flags_of(jnp, x, finite, unit_range, non_negative))


def positive_int(value: Any, name: str, where: str, *, minimum: int = 1) -> int:
    """A static integer option ``>= minimum``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{where}: `{name}` must be a Python int (it sets array shapes), "
                        f"got {value!r}.")
    if value < minimum:
        raise ValueError(f"{where}: `{name}` must be >= {minimum}, got {value}.")
    return int(value)


def positive_float(value: Any, name: str, where: str) -> float:
    """A static float option ``> 0``."""
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{where}: `{name}` is static (a Python number) and cannot be "
                        f"traced; close over it instead of passing it as a `jit` argument.")
    if isinstance(value, str | bytes) or holds_bool(value):  # float("0.5") would pass
        raise TypeError(f"{where}: `{name}` must be a number, got {value!r}.")
    try:
        out = float(value)
    except OverflowError as err:  # an int past a float's range
        raise ValueError(f"{where}: `{name}` must be a finite number > 0, got "
                         f"{value!r:.80}.") from err
    except (TypeError, ValueError) as err:
        raise TypeError(f"{where}: `{name}` must be a number, got {value!r}.") from err
    if not np.isfinite(out) or out <= 0:
        raise ValueError(f"{where}: `{name}` must be a finite number > 0, got {value!r}.")
    return out


def spacing(value: Any, where: str) -> tuple[float, float, float]:
    """Voxel spacing ``(sd, sh, sw)`` in millimetres: a positive scalar or 3-sequence."""
    if traced(value):
        raise TypeError(f"{where}: `spacing` is static (it sets kernels and sample "
                        f"positions) and cannot be traced; close over it instead of passing "
                        f"it as a `jit` argument.")
    # a string would parse, a bool pass as 1 (also beside numbers, which NumPy promotes)
    try:
        kind = np.asarray(value).dtype.kind
    except ValueError:  # a ragged nested list
        kind = "O"
    if holds_bool(value) or kind not in "iuf":
        raise TypeError(f"{where}: `spacing` must be a number or 3 numbers (d, h, w) in mm, "
                        f"got {value!r}.")
    vals = np.broadcast_to(np.asarray(value, dtype=float), (3,)) if np.ndim(value) == 0 \
        else np.asarray(value, dtype=float)
    if vals.shape != (3,):
        raise ValueError(f"{where}: `spacing` must be a number or 3 numbers (d, h, w) in mm, "
                         f"got {value!r}.")
    if not np.all(np.isfinite(vals)) or np.any(vals <= 0):
        raise ValueError(f"{where}: `spacing` must be finite and > 0, got {value!r}.")
    return tuple(float(v) for v in vals)


def option(value: Any, table: Mapping[str, Any], name: str, where: str, *,
           hint: str = "") -> Any:
    """Look ``value`` up in a dispatch table, listing the valid names on failure; a value
    that is not a name (an array, a parameter module) is named by its type, followed by
    ``hint`` (where what it is goes instead), not printed whole."""
    valid = ", ".join(repr(k) for k in table)
    if not isinstance(value, str):
        # an argument by its name; a description ("dataset") as words
        label = f"`{name}`" if name.isidentifier() else f"the {name}"
        raise TypeError(f"{where}: {label} must name an option, one of {valid}, got "
                         f"{type(value).__name__}{'; ' + hint if hint else ''}.")
    if value not in table:
        raise ValueError(f"{where}: unknown {name} {value!r}; valid values are {valid}.")
    return table[value]


def broadcasts(shape: tuple[int, ...], target: tuple[int, ...]) -> bool:
    """Whether ``shape`` broadcasts to ``target`` (without growing it)."""
    try:
        return np.broadcast_shapes(shape, target) == tuple(target)
    except ValueError:
        return False
