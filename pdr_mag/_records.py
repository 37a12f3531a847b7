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
(``record[0]`` is the record).  :func:`check_numbers` is the settings' shared input check.
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


def _fill(rec: np.ndarray, settings) -> None:
    for f in fields(settings):
        v = getattr(settings, f.name)
        if "kernel" in f.metadata:
            name, convert = f.metadata["kernel"]
            rec[name] = convert(v)
        elif is_dataclass(v):
            _fill(rec[f.name], v)
        else:
            rec[f.name] = v


def settings_record(settings) -> np.ndarray:
    """``settings`` as the one-element array of :func:`settings_dtype` that a kernel takes."""
    rec = np.zeros(1, dtype=settings_dtype(type(settings)))
    _fill(rec, settings)
    return rec


def check_numbers(settings, positive: tuple = (), skip: tuple = ()) -> None:
    """``ValueError`` naming the first number field of ``settings`` that is not finite and ≥ 0, or, for the
    names in ``positive``, not > 0 (nested settings and the names in ``skip`` are not looked at)."""
    where = type(settings).__name__
    for f in fields(settings):
        v = getattr(settings, f.name)
        if f.name in skip or is_dataclass(v):
            continue
        if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
            raise ValueError(f"{where}.{f.name}: expected a non-negative finite number, got {v!r}")
        if f.name in positive and not v > 0:
            raise ValueError(f"{where}.{f.name}: expected a positive number, got {v!r}")
