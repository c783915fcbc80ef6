"""Array checks shared by the model types, readers and retargeters.

Each helper returns a *read-only view or copy* of the array (never the caller's
array with its flags changed) and raises a typed error whose message names the
argument, what was wrong and how to fix it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from .errors import ConfigError, IndexRangeError, InputError, NonFiniteError, ShapeError

_T = TypeVar("_T")


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only view of ``array`` (the caller's array keeps its own flags)."""
    view = array.view()
    view.flags.writeable = False
    return view


def as_array(value: object, name: str) -> np.ndarray:
    """``np.asarray(value)``, with a :class:`ShapeError` for input numpy cannot turn into an
    array (ragged nested lists, objects whose ``__array__`` fails)."""
    if isinstance(value, np.ndarray):
        return value
    try:
        return np.asarray(value)
    except Exception as exc:
        raise ShapeError(
            f"{name}: could not read as an array ({exc}); pass a rectangular numpy array"
        ) from None


def as_float_array(
    value: object,
    name: str,
    shape: Sequence[int | None],
    *,
    allow_nan: bool = False,
    dtype: npt.DTypeLike = np.float64,
    copy: bool = False,
) -> np.ndarray:
    """Validate a floating-point array of the given shape (``None`` = any length).

    float32 input is accepted and converted; memory-mapped float64 input is viewed,
    not copied, so long sequences stay on disk. ``allow_nan`` permits NaN (missing
    samples) but never infinity.
    """
    arr = as_array(value, name)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ShapeError(
            f"{name}: expected numbers, got dtype {arr.dtype}; pass a float array of shape {_fmt(shape)}"
        )
    if np.iscomplexobj(arr):
        raise ShapeError(f"{name}: complex values are not supported; pass real coordinates")
    check_shape(arr, name, shape)
    if arr.dtype != dtype:
        arr = arr.astype(dtype)
    elif copy:
        arr = arr.copy()
    check_finite(arr, name, allow_nan=allow_nan)
    return readonly(arr)


def as_index_array(
    value: object, name: str, shape: Sequence[int | None], upper: int | None = None
) -> np.ndarray:
    """Validate an integer index array with every entry in ``[0, upper)``."""
    arr = as_array(value, name)
    if arr.size == 0 and arr.dtype.kind not in "iu":
        arr = arr.astype(np.int64)
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise ShapeError(f"{name}: indices must be whole numbers, got non-integer floats")
    elif arr.dtype.kind not in "iu":
        raise ShapeError(f"{name}: expected integer indices, got dtype {arr.dtype}")
    check_shape(arr, name, shape)
    arr = arr.astype(np.int64)
    if arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < 0:
            raise IndexRangeError(
                f"{name}: negative index {lo}; indices are 0-based and must be >= 0"
            )
        if upper is not None and hi >= upper:
            raise IndexRangeError(
                f"{name}: index {hi} out of range for {upper} items (valid 0..{upper - 1}); "
                "check that the indices refer to this mesh (0-based)"
            )
    return readonly(arr)


def check_shape(arr: np.ndarray, name: str, shape: Sequence[int | None]) -> None:
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise ShapeError(f"{name}: expected shape {_fmt(shape)}, got {tuple(arr.shape)}")


def sum_finite(arr: np.ndarray) -> bool:
    """True when the sum of the float array ``arr`` is finite, which proves every value finite
    (a NaN or an infinity makes the sum NaN or infinite): one pass, no boolean temporary, no
    warning. False proves nothing (finite values whose sum overflows give it too)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.isfinite(np.sum(arr)))


def all_finite(arr: np.ndarray) -> bool:
    """Whether every value of the float array ``arr`` is finite: :func:`sum_finite`, and the
    exact test only when the sum is not finite."""
    return sum_finite(arr) or bool(np.isfinite(arr).all())


def check_finite(arr: np.ndarray, name: str, *, allow_nan: bool = False) -> None:
    if arr.dtype.kind != "f" or (not allow_nan and all_finite(arr)):
        return
    if allow_nan:
        bad = np.isinf(arr)
        what = "infinite values"
    else:
        bad = ~np.isfinite(arr)
        what = "NaN or infinite values"
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        hint = " (missing samples must be NaN, never inf)" if allow_nan else ""
        raise NonFiniteError(f"{name}: {int(bad.sum())} {what}, first at index {first}{hint}")


def as_names(
    value: Any, name: str, count: int | None = None, *, default_prefix: str | None = None
) -> tuple[str, ...]:
    """Validate a sequence of unique, non-empty string names (optionally of a given count)."""
    if value is None:
        if default_prefix is None or count is None:
            raise InputError(f"{name}: names are required")
        return tuple(f"{default_prefix}{i}" for i in range(count))
    if isinstance(value, str):
        raise InputError(f"{name}: expected a sequence of names, got a single string {value!r}")
    if isinstance(value, np.ndarray):
        items = value.ravel().tolist()
    else:
        try:
            items = list(value)
        except Exception:
            raise InputError(
                f"{name}: expected a sequence of names, got {type(value).__name__}"
            ) from None
    for v in items:
        if not isinstance(v, str):
            raise InputError(f"{name}: names must be strings, got {v!r} ({type(v).__name__})")
    names = tuple(items)
    if count is not None and len(names) != count:
        raise ShapeError(f"{name}: expected {count} names, got {len(names)}")
    for n in names:
        if not n.strip():
            raise InputError(f"{name}: empty name; every entry needs a non-blank name")
    seen: dict[str, int] = {}
    for i, n in enumerate(names):
        if n in seen:
            raise InputError(
                f"{name}: duplicate name {n!r} at positions {seen[n]} and {i}; names must be unique"
            )
        seen[n] = i
    return names


def as_fps(value: Any, name: str = "fps") -> float:
    try:
        fps = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(
            f"{name}: expected a positive number of frames per second, got {value!r}"
        ) from None
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"{name}: expected a positive number of frames per second, got {value!r}")
    return fps


def short_repr(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for error messages (never raises)."""
    try:
        text = repr(value)
    except Exception:  # a repr that fails must not hide the real error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _fmt(shape: Sequence[int | None]) -> str:
    return (
        "("
        + ", ".join("*" if s is None else str(s) for s in shape)
        + ("," if len(shape) == 1 else "")
        + ")"
    )


def check_number(
    value: object,
    name: str,
    *,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
    open_low: bool = False,
    allow_none: bool = False,
    choices: Sequence[str] = (),
) -> int | float | str | None:
    """A numeric parameter (of a retargeter, reader...) checked for type, finiteness and range.

    Returns the value as ``int`` or ``float`` (None passes when ``allow_none``, and one of the
    strings ``choices`` is returned as is, for parameters such as ``"auto"`` or a number);
    raises :class:`InputError` naming ``name``, the valid values and the value given.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, str) and value in choices:
        return value
    want = "a whole number" if integer else "a finite number"
    if choices:
        want = f"{', '.join(map(repr, choices))} or {want}"
    limits = ([f"{'>' if open_low else '>='} {low}"] if low is not None else []) + (
        [f"<= {high}"] if high is not None else []
    )
    message = f"{name}: expected {want}{' ' + ' and '.join(limits) if limits else ''}, got {short_repr(value)}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise InputError(message)
    try:
        as_float = float(value)
    except OverflowError:
        raise InputError(message) from None
    if not np.isfinite(as_float) or (integer and not as_float.is_integer()):
        raise InputError(message)
    number = int(value) if integer else as_float
    if (low is not None and (number < low or (open_low and number == low))) or (
        high is not None and number > high
    ):
        raise InputError(message)
    return number


def did_you_mean(
    name: object, choices: Iterable[object], *, n: int = 3, cutoff: float = 0.6
) -> str:
    """``" (did you mean 'x'?)"`` naming the choices closest to ``name`` (difflib), or ``""``.

    Matching ignores case (``"JawOpen"`` suggests ``"jawOpen"``) and also tries the name
    with ``-``/``_`` swapped, so a typo in a method, parameter, case, format or shape name
    gets the likely intended one.
    """
    import difflib

    if not isinstance(name, str) or not name:
        return ""
    pool = [c for c in dict.fromkeys(choices) if isinstance(c, str)]
    if not pool:
        return ""
    lowered: dict[str, str] = {}
    for c in pool:
        lowered.setdefault(c.lower(), c)
    keys = [name.lower(), name.lower().replace("-", "_"), name.lower().replace("_", "-")]
    found: list[str] = []
    for key in keys:
        if key in lowered and key != name:
            found.append(lowered[key])
        found.extend(
            lowered[m] for m in difflib.get_close_matches(key, list(lowered), n=n, cutoff=cutoff)
        )
    found = [f for f in dict.fromkeys(found) if f != name][:n]
    if not found:
        return ""
    return " (did you mean " + " or ".join(repr(f) for f in found) + "?)"


def check_choice(value: object, name: str, choices: Sequence[str]) -> str:
    """A string parameter that must be one of ``choices`` (InputError listing them otherwise)."""
    if not isinstance(value, str) or value not in choices:
        raise InputError(
            f"{name}: expected one of {', '.join(map(repr, choices))}, got {short_repr(value)}{did_you_mean(value, choices)}"
        )
    return value


def check_bool(value: object, name: str) -> bool:
    """A flag parameter: ``True``/``False`` (also ``np.bool_`` and the integers 0 and 1).

    Anything else (an array, a string, None...) is an :class:`InputError` naming ``name``;
    truthiness is never used, so ``"no"`` or an array cannot pass as a flag.
    """
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return bool(value)
    raise InputError(f"{name}: expected True or False, got {short_repr(value)}")


def check_param(
    check: Callable[..., _T], value: object, name: str, *args: Any, **kwargs: Any
) -> _T:
    """``check(value, name, ...)`` (:func:`check_number`, :func:`check_choice`, :func:`check_bool`)
    for a retargeter's constructor parameter: a bad value is a :class:`ConfigError` naming
    the parameter, the valid values and the value given."""
    try:
        return check(value, name, *args, **kwargs)
    except InputError as exc:
        raise ConfigError(str(exc)) from None
