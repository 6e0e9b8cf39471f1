"""Input checking shared by the core: turn user values into arrays or raise ValueError saying what to fix."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def as_vector(value, length: int, name: str) -> np.ndarray:
    """Return ``value`` as a finite float vector of ``length`` entries (a scalar is broadcast)."""
    array = np.array(value, dtype=float, ndmin=1)
    if array.size == 1 and length != 1:
        array = np.full(length, float(array.ravel()[0]))
    if array.ndim != 1 or array.size != length:
        raise ValueError(
            f'{name} must have {length} entries, got shape {np.shape(value)}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite, got {array.tolist()}')
    return array


def as_matrix(value, shape: tuple[int, int], name: str) -> np.ndarray:
    """Return ``value`` as a finite float matrix of ``shape``.

    Accepts a matrix, a flat row-major list of rows*cols numbers (how ROS parameters carry
    matrices), a vector of ``shape[0]`` numbers for a square diagonal matrix, or a scalar
    for a multiple of the identity.
    """
    rows, cols = shape
    array = np.array(value, dtype=float)
    if array.size == 1 and rows == cols:
        array = float(array.ravel()[0]) * np.eye(rows)
    elif array.ndim == 1 and array.size == rows * cols:
        array = array.reshape(rows, cols)
    elif array.ndim == 1 and rows == cols and array.size == rows:
        array = np.diag(array)
    if array.shape != (rows, cols):
        raise ValueError(
            f'{name} must be a {rows}x{cols} matrix (or {rows * cols} numbers row-major'
            + (f', {rows} diagonal entries or a scalar' if rows == cols else '')
            + f'), got shape {np.shape(value)}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite')
    return array


def check_covariance(matrix: np.ndarray, name: str, allow_singular: bool = False) -> np.ndarray:
    """Check that ``matrix`` is symmetric and positive definite (semi-definite if allowed)."""
    if not np.allclose(matrix, matrix.T, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(matrix).max())):
        raise ValueError(f'{name} must be symmetric')
    eigenvalues = np.linalg.eigvalsh(matrix)
    smallest = float(eigenvalues.min())
    if allow_singular:
        if smallest < -1e-12 * max(1.0, float(eigenvalues.max())):
            raise ValueError(
                f'{name} must be positive semi-definite; smallest eigenvalue is {smallest:g}')
    elif smallest <= 0.0:
        raise ValueError(
            f'{name} must be positive definite; smallest eigenvalue is {smallest:g} '
            '(use strictly positive variances)')
    return 0.5 * (matrix + matrix.T)


def check_positive(value: float, name: str, strict: bool = True) -> float:
    """Check a finite scalar is > 0 (or >= 0 when not strict)."""
    number = float(value)
    if not np.isfinite(number) or number < 0.0 or (strict and number == 0.0):
        raise ValueError(f'{name} must be {"> 0" if strict else ">= 0"}, got {value!r}')
    return number


def check_choice(value: str, choices: Sequence[str], name: str) -> str:
    """Check ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f'{name} must be one of {", ".join(choices)}; got {value!r}')
    return value
