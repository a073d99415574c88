"""Input checks shared by the core: one checker per kind of input, typed errors.

Each checker validates one public input at the boundary and returns it in the form
the computation uses (a float, an int, a C-contiguous float array). Errors subclass
the builtin ``ValueError`` (and ``TypeError`` where a keyword is not accepted), so a
caller may catch either the builtin or the project's type; messages say what was
expected and what was found. Inside the core, after these checks, shapes are trusted.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

__all__ = [
    "InputError",
    "OptionError",
    "finite_array",
    "nonnegative_float",
    "positive_float",
    "positive_int",
    "sample_rate",
    "trace_1d",
    "traces_2d",
]


class InputError(ValueError):
    """An input the core cannot use (a ``ValueError``)."""


class OptionError(InputError, TypeError):
    """A keyword argument the chosen method does not take (a ``ValueError`` and a ``TypeError``)."""


def positive_float(name: str, value, *, error: type[ValueError] = InputError) -> float:
    """Return ``value`` as a positive finite float.

    Parameters
    ----------
    name : str
        Name of the argument, used in the message.
    value : object
        Anything ``float()`` accepts (a number, a numeric string).
    error : type, optional
        Exception class to raise, a ``ValueError`` subclass (default :class:`InputError`).

    Raises
    ------
    InputError
        ``"{name} must be a positive finite number, got {value!r}"``.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a positive finite number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise error(f"{name} must be a positive finite number, got {value!r}")
    return v


def nonnegative_float(name: str, value, *, error: type[ValueError] = InputError) -> float:
    """Return ``value`` as a finite float ``>= 0`` (as :func:`positive_float`, zero allowed)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a finite number >= 0, got {value!r}") from None
    if not math.isfinite(v) or v < 0.0:
        raise error(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def positive_int(name: str, value, *, error: type[ValueError] = InputError) -> int:
    """Return ``value`` as a positive int; bools and non-integral numbers are refused.

    Raises
    ------
    InputError
        ``"{name} must be a positive integer, got {value!r}"``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral) or value <= 0:
        raise error(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def sample_rate(value, *, name: str = "sample_rate_hz",
                error: type[ValueError] = InputError) -> float:
    """Return a sample rate (Hz) as a positive finite float.

    Only real numbers are accepted (not bools, strings or None), so a sample rate
    read from the wrong field fails here rather than as a rate of 1 Hz.

    Raises
    ------
    InputError
        ``"sample_rate_hz must be a positive finite real number, found ..."`` (wrong type)
        or ``"sample_rate_hz must be positive and finite, found ..."``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise error(
            f"{name} must be a positive finite real number, "
            f"found {value!r} of type {type(value).__name__}"
        )
    fs = float(value)
    if not (math.isfinite(fs) and fs > 0.0):
        raise error(f"{name} must be positive and finite, found {fs!r}")
    return fs


def finite_array(name: str, value, *, shape: tuple | None = None,
                 error: type[ValueError] = InputError) -> np.ndarray:
    """Return ``value`` as a finite float64 array, of ``shape`` if one is given.

    Raises
    ------
    InputError
        ``"{name} must have shape {shape}, got {found}"`` or
        ``"{name} contains non-finite entries"``.
    """
    a = np.asarray(value, dtype=float)
    if shape is not None and a.shape != tuple(shape):
        raise error(f"{name} must have shape {tuple(shape)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise error(f"{name} contains non-finite entries")
    return a


def _real_array(x, name, error):
    y = np.asarray(x)
    if y.dtype.kind == "c":
        raise error(f"{name} must be real, found complex dtype {y.dtype}")
    if y.dtype.kind not in "biuf":
        try:
            y = y.astype(np.float64)
        except (TypeError, ValueError) as exc:
            raise error(f"{name} must be a real numeric array, found dtype {y.dtype}") from exc
    return y


def _finite_rows(y, name, error):
    finite = np.isfinite(y)
    if not finite.all():
        bad_rows = np.flatnonzero(~finite.all(axis=1))
        raise error(
            f"{name} must be finite, found {int((~finite).sum())} NaN or Inf value(s) "
            f"(non-finite) in {bad_rows.size} trace(s), first in trace {int(bad_rows[0])}"
        )


def traces_2d(x, name: str = "traces", *, min_samples: int = 1, promote_1d: bool = True,
              dtype=None, error: type[ValueError] = InputError) -> np.ndarray:
    """Validate a batch of traces once, at the boundary.

    Parameters
    ----------
    x : array_like, shape (n_traces, n_samples) or (n_samples,)
        Real traces; a 1-D array is one trace, promoted to a batch of one if
        ``promote_1d`` (refused otherwise).
    name : str
        Name used in error messages.
    min_samples : int
        Fewest samples per trace accepted.
    promote_1d : bool
        Accept a single 1-D trace as a batch of one.
    dtype : numpy dtype, optional
        Output dtype. Default: float32 input stays float32, any other becomes float64.
    error : type, optional
        Exception class, a ``ValueError`` subclass (default :class:`InputError`).

    Returns
    -------
    y : ndarray, shape (n_traces, n_samples)
        C-contiguous, finite.

    Raises
    ------
    InputError
        Wrong number of dimensions, fewer than ``min_samples`` samples, a complex or
        non-numeric dtype, or NaN / Inf values.
    """
    y = _real_array(x, name, error)
    if y.ndim == 1 and promote_1d:
        y = y[np.newaxis, :]
    if y.ndim != 2:
        what = ("a 2-D array of shape (n_traces, n_samples)"
                + (" or a 1-D array of shape (n_samples,)" if promote_1d else ""))
        raise error(f"{name} must be {what}, found ndim={y.ndim} with shape {y.shape}")
    _min_samples(y, name, min_samples, error)
    if dtype is None:
        dtype = np.float32 if y.dtype == np.float32 else np.float64
    y = np.ascontiguousarray(y, dtype=dtype)
    _finite_rows(y, name, error)
    return y


def trace_1d(x, name: str = "trace", *, min_samples: int = 1, dtype=np.float64,
             error: type[ValueError] = InputError) -> np.ndarray:
    """Validate one trace, shape (n_samples,): as :func:`traces_2d` for a single row.

    Returns
    -------
    y : ndarray, shape (n_samples,)
    """
    y = _real_array(x, name, error)
    if y.ndim != 1:
        raise error(f"{name} must be a 1-D array of shape (n_samples,), "
                    f"found ndim={y.ndim} with shape {y.shape}")
    _min_samples(y[np.newaxis, :], name, min_samples, error)
    y = np.ascontiguousarray(y, dtype=dtype)
    _finite_rows(y[np.newaxis, :], name, error)
    return y


def _min_samples(y, name, min_samples, error):
    if y.shape[1] < min_samples:
        raise error(
            f"{name} must have at least {min_samples} samples per trace, "
            f"found {y.shape[1]} (shape {y.shape})"
        )
