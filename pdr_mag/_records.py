"""Settings dataclasses as the records the compiled kernels read: the one helper that builds them all.

A numba kernel reads its settings from a numpy record (named fields, read at native speed, compiled
against with ``cache=True``).  Every such record — the fusion filter's, the interference detectors', the
online calibrator's — is built here from its frozen settings dataclass, so a setting has one name and one
definition, and a new setting is a new dataclass field and nothing else:

* a ``float`` field becomes a ``float64`` field of the same name, an ``int`` an ``int64``, a ``bool`` a
  ``bool``;
* a field whose type is itself a settings dataclass (a group of settings) becomes a nested record of the
  same name (the kernel reads ``p.mag.gate``);
* a field declared with :func:`kernel_field` reaches the kernel under another name, in the units the
  kernel computes in (``noise_deg`` → ``noise_rad``, a rate → its period), converted by the function given
  there.

:func:`settings_dtype` is the record's dtype, :func:`settings_record` the one-element array a kernel takes
(``record[0]`` is the record).  :func:`check_numbers` is the settings' shared input check;
:func:`default_settings` a class's defaults, built and checked once.
"""

from __future__ import annotations

import functools
import math
import typing
from dataclasses import field, fields, is_dataclass

import numpy as np

_SCALARS = {float: np.float64, int: np.int64, bool: np.bool_}


def kernel_field(default, name: str, convert):
    """A dataclass field that the kernel reads as ``name``, with the value ``convert(setting)``.

    Examples
    --------
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class S:
    ...     noise_deg: float = kernel_field(5.0, "noise_rad", math.radians)
    >>> settings_dtype(S).names
    ('noise_rad',)
    """
    return field(default=default, metadata={"kernel": (name, convert)})


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


@functools.cache
def settings_dtype(cls) -> np.dtype:
    """The record dtype of settings dataclass ``cls`` (the module docstring's rules), aligned like C."""
    hints = _hints(cls)
    spec = []
    for f in fields(cls):
        kind = hints[f.name]
        name = f.metadata["kernel"][0] if "kernel" in f.metadata else f.name
        if is_dataclass(kind):
            spec.append((name, settings_dtype(kind)))
        elif "kernel" in f.metadata:
            spec.append((name, np.float64))
        elif kind in _SCALARS:
            spec.append((name, _SCALARS[kind]))
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: no kernel type for {kind!r}")
    return np.dtype(spec, align=True)


def _values(settings) -> tuple:
    """The record's values, in its fields' order (nested settings as nested tuples)."""
    out = []
    for f in fields(settings):
        v = getattr(settings, f.name)
        if "kernel" in f.metadata:
            out.append(f.metadata["kernel"][1](v))
        elif is_dataclass(v):
            out.append(_values(v))
        else:
            out.append(v)
    return tuple(out)


@functools.lru_cache(maxsize=64)
def _record(settings) -> np.ndarray:
    return np.array([_values(settings)], dtype=settings_dtype(type(settings)))


def settings_record(settings) -> np.ndarray:
    """``settings`` as the one-element array of :func:`settings_dtype` that a kernel takes (a fresh copy;
    the settings are frozen, so the record of equal settings is built once)."""
    return copy_record(_record(settings))


def copy_record(rec: np.ndarray) -> np.ndarray:
    """A copy of a structured array as a copy of its bytes (numpy's copy of nested records goes field by
    field, tens of µs for the filter's state)."""
    out = np.empty(rec.shape, dtype=rec.dtype)
    out.view(np.uint8)[:] = rec.view(np.uint8)
    return out


@functools.cache
def default_settings(cls):
    """``cls()`` of a frozen settings dataclass, built (and its numbers checked) once: every run that is
    given no settings takes the defaults, and the checks of a group of groups cost ~0.1 ms."""
    return cls()


def check_numbers(settings, positive: tuple = (), signed: tuple = ()) -> None:
    """``ValueError`` naming the first field of ``settings`` that is wrong: a group of settings (a field
    declared as a dataclass, or as one or None) that is not of its declared class, or a number that is not
    finite and ≥ 0 — for the names in ``positive``, not > 0; for those in ``signed``, not finite (the numbers
    inside a group are its own class's to check)."""
    where = type(settings).__name__
    hints = _hints(type(settings))
    for f in fields(settings):
        v = getattr(settings, f.name)
        kind = hints.get(f.name)
        optional = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(optional) == 1 and len(typing.get_args(kind)) == 2 and is_dataclass(optional[0]):
            if v is None:
                continue
            kind = optional[0]
        if isinstance(kind, type) and is_dataclass(kind):
            if not isinstance(v, kind):
                raise ValueError(f"{where}.{f.name}: expected a {kind.__name__}, got {type(v).__name__}")
            continue
        if not (isinstance(v, int | float) and math.isfinite(v) and (v >= 0 or f.name in signed)):
            raise ValueError(f"{where}.{f.name}: expected a non-negative finite number, got {v!r}")
        if f.name in positive and not v > 0:
            raise ValueError(f"{where}.{f.name}: expected a positive number, got {v!r}")
